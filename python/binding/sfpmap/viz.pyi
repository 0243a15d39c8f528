# Types of sfpmap.viz (python -m sfpmap.viz); the module's docstring says what it does.
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

import sfpmap

__all__ = [
    "LEVEL_COLORS", "MAX_CAMERAS", "Summary", "main", "read_tum", "record",
    "rotation_matrix", "world_from_cam",
]

LEVEL_COLORS: List[Tuple[int, int, int]]
ESTIMATE_COLOR: Tuple[int, int, int]
TRUTH_COLOR: Tuple[int, int, int]
ERROR_COLOR: Tuple[int, int, int]
MAX_CAMERAS: int
UNIX_STAMPS_FROM: float
MAX_STAMP: float

@dataclass
class Summary:
    points_per_level: Dict[int, int] = ...
    cameras: int = ...
    estimates: int = ...
    truths: int = ...
    errors: int = ...
    inliers: int = ...
    trajectory: int = ...
    def as_dict(self) -> Dict[str, Any]: ...

def rotation_matrix(qw: float, qx: float, qy: float, qz: float) -> npt.NDArray[np.float64]: ...
def world_from_cam(colmap: Sequence[float]) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def read_tum(path: str) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def record(
    map_path: str,
    out: str,
    *,
    poses: Optional[str] = None,
    gt: Optional[str] = None,
    trajectory: Optional[str] = None,
    inliers: Optional[Tuple[str, sfpmap.Localization, sfpmap.Camera]] = None,
    query_cameras: Optional[Union[Dict[str, Any], Sequence[Tuple[str, Any]], sfpmap.Camera, str, Dict[str, Any]]] = None,
    max_points: Optional[int] = None,
    force: bool = False,
) -> Summary: ...
def main(argv: Optional[Sequence[str]] = None) -> int: ...
