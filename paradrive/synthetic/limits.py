"""What the synthetic street's numbers may be (:data:`LIMITS`), and the bound every loop that
lays the street out runs within (:func:`along`): a street is finite, so its generation is too."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class Limit:
    """The closed range ``[low, high]`` a parameter of the street takes; NaN and infinities are
    never in it."""

    low: float
    high: float
    unit: str = ""

    def admits(self, value: float) -> bool:
        return math.isfinite(value) and self.low <= value <= self.high

    @property
    def text(self) -> str:
        return f"[{_number(self.low)}, {_number(self.high)}]" + (f" {self.unit}" if self.unit else "")


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(float(value))


# The ranges of SyntheticStreet's numbers (its arguments' names). Every loop that places objects
# runs over the street's length, so these bound the work: 3000 frames at 70 m/s and 10 frames a
# second drive 21 km, a street of some 30,000 boxes that is laid out in seconds.
LIMITS: dict[str, Limit] = {
    # np.random.SeedSequence takes any non-negative integer; the textures multiply the seed by
    # 1000 in int64, and 32 bits are every seed a generator is usually given
    "seed": Limit(0, 2**32 - 1),
    "frames": Limit(1, 3000),                 # 5 minutes at 10 Hz (a Waymo segment: 200)
    "width": Limit(1, 3840, "px"),            # a 4K UHD frame at most
    "height": Limit(1, 2160, "px"),
    "curvature": Limit(-0.01, 0.01, "1/m"),   # a radius of 100 m at least
    "speed_mps": Limit(0.0, 70.0, "m/s"),     # 252 km/h, beyond what a road log holds
    "fps": Limit(1.0, 100.0, "frames a second"),
}
# the longest drive (m): the limits' own, 2999 frames at 70 m/s and 10 frames a second
MAX_TRAVEL_M = 21_000.0

def check_values(values: Mapping[str, float]) -> None:
    """Refuse (ValueError, one line: the parameter, its value and its range) a number of the
    street outside :data:`LIMITS` (NaN and infinities included) or a whole number given as a
    fraction."""
    for name, value in values.items():
        limit = LIMITS[name]
        number = float(value)
        if not limit.admits(number):
            raise ValueError(f"synthetic street: {name}={value} is outside {limit.text}")
        if name in ("seed", "frames", "width", "height") and not number.is_integer():
            raise ValueError(f"synthetic street: {name}={value} is not a whole number")


def along(s: float, s_max: float, min_step: float) -> range:
    """The most steps a placement loop from ``s`` to ``s_max`` can take when each step moves at
    least ``min_step`` metres: every such loop runs over this range, so none can run without
    end (a street is finite and at most :data:`MAX_TRAVEL_M` plus its margins long)."""
    if not (math.isfinite(s) and math.isfinite(s_max)) or s_max - s > MAX_TRAVEL_M + 1000.0:
        raise ValueError(f"synthetic street: cannot lay out objects from s={s} to s={s_max} m; "
                         f"a street is at most {MAX_TRAVEL_M:.0f} m long")
    return range(max(0, math.ceil((s_max - s) / min_step)) + 1)
