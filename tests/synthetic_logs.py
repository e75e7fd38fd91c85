"""A synthetic street as a log source for the ingest tests, with random LiDAR points around the ego."""

from __future__ import annotations

import dataclasses

import numpy as np

from paradrive.ingest import export


def street_log(seed: int, frames: int, width: int, height: int, cameras, *, lidar_seed: int,
               lidar_points: int, lidar_extent_m: float):
    """export.LogSource of a SyntheticStreet whose LiDAR is random points in a box around the ego."""
    from paradrive.synthetic import SyntheticStreet

    street = SyntheticStreet("demo", seed=seed, frames=frames, width=width, height=height,
                             cameras=cameras)
    src = export.source_from_street(street)
    lo, hi = [-lidar_extent_m, -lidar_extent_m, -1.5], [lidar_extent_m, lidar_extent_m, 3.0]

    def lidar(i):
        local = np.random.default_rng(lidar_seed + i).uniform(lo, hi, (lidar_points, 3))
        return local @ src.ego2world[i][:3, :3].T + src.ego2world[i][:3, 3]

    return dataclasses.replace(src, lidar=lidar)
