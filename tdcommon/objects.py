"""The one object vocabulary: the paper's categories, the tracking dimension and keypoint count of each.

``dlo`` a deformable linear object (rope, cable), ``bdlo`` a branched one (wire harness), ``cloth`` a sheet
(fabric, towel). Configs, the simulator, episodes and the tracker all name an object's kind by its category;
the tracker's 1D / 2D dimension is derived from it here.
"""

from __future__ import annotations

from typing import Literal

Category = Literal["dlo", "bdlo", "cloth"]
Dimension = Literal["1d", "2d"]

CATEGORIES: tuple[Category, ...] = ("dlo", "bdlo", "cloth")
DIMENSION: dict[str, Dimension] = {"dlo": "1d", "bdlo": "1d", "cloth": "2d"}
DEFAULT_KEYPOINTS: dict[str, int] = {"dlo": 20, "bdlo": 25, "cloth": 36}  # cloth: a 6 x 6 grid


def dimension(category: str) -> Dimension:
    """"1d" or "2d" for a category; ValueError naming the known ones otherwise."""
    try:
        return DIMENSION[category]
    except KeyError:
        raise ValueError(f"unknown object category {category!r} (expected one of {', '.join(CATEGORIES)})") from None


def default_keypoints(category: str) -> int:
    """The keypoint count tracked for a category unless the config says otherwise."""
    dimension(category)
    return DEFAULT_KEYPOINTS[category]
