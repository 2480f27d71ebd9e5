"""One Taichi runtime per process, started on first use and never at import time."""
from __future__ import annotations

_settings: dict | None = None


def init_taichi(arch: str = "cpu", num_threads: int = 1, debug: bool = False) -> dict:
    """Start Taichi in this process (idempotent).

    Args:
        arch: ``"cpu"``, ``"cuda"`` or ``"gpu"`` (Taichi picks a GPU backend).
        num_threads: CPU threads Taichi may use; one keeps results bit-for-bit reproducible
            (atomic adds in particle-to-grid transfers run in a fixed order).
        debug: Taichi's bounds-checking mode.

    Returns the settings in force. A second call with other settings raises: ``ti.init`` would
    free every field that the solvers of this process hold.
    """
    global _settings
    settings = {"arch": arch, "num_threads": num_threads, "debug": debug}
    if _settings is not None:
        if settings != _settings:
            raise RuntimeError(f"Taichi already started with {_settings}; cannot restart with {settings}")
        return _settings
    import taichi as ti

    ti.init(
        arch={"cpu": ti.cpu, "cuda": ti.cuda, "gpu": ti.gpu}[arch],
        cpu_max_num_threads=num_threads,
        debug=debug,
        default_fp=ti.f32,
        default_ip=ti.i32,
        random_seed=0,
        log_level=ti.WARN,
        offline_cache=True,
    )
    _settings = settings
    return _settings


def ensure_taichi() -> None:
    """Start Taichi with the defaults unless this process already did."""
    if _settings is None:
        init_taichi()
