# Types of sfpmap.batch (python -m sfpmap.batch); the module's docstring says what it does.
from typing import Any, Callable, Dict, List, Optional, Tuple

__all__ = ["main", "run", "run_place", "read_manifest", "parse_variant", "parse_size", "job_of"]

_Row = Dict[str, Any]

def main(argv: Optional[List[str]] = None) -> int: ...
def run(
    manifest: str,
    out: str,
    *,
    address: Optional[str] = None,
    cpus_per_place: int = 1,
    retries: int = 3,
    work_dir: Optional[str] = None,
    force: bool = False,
    pass_credentials: bool = False,
    report_path: Optional[str] = None,
    progress: Optional[Callable[[int, int, _Row], None]] = None,
) -> Dict[str, Any]: ...
def run_place(
    place: Dict[str, Any], out: str, work_dir: Optional[str] = None, threads: int = 1, force: bool = False
) -> _Row: ...
def read_manifest(manifest: str) -> Tuple[List[Dict[str, Any]], List[_Row]]: ...
def parse_variant(name: Any) -> Dict[str, Any]: ...
def parse_size(value: Any) -> int: ...
def job_of(metadata: Dict[str, Any]) -> Optional[Dict[str, Any]]: ...
