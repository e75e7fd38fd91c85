"""Procedural driving street rendered by an exact analytic ray caster (demo input and ground truth)."""

from paradrive.synthetic.street import CameraSpec, SyntheticStreet

__all__ = ["CameraSpec", "SyntheticStreet"]
