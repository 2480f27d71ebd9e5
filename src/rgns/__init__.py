"""rgns: the Reversible Graph Network Simulator and its experiment framework."""
from pathlib import Path

__version__ = "0.1.0"


def config_dir() -> Path:
    """The Hydra config folder (``train.yaml``, ``evaluate.yaml``, ``generate.yaml`` and the groups).

    It ships inside the package as ``rgns/conf``; in the repository that is a link to ``conf/``,
    so an editable install reads (and edits reach) the repo's configs. Compose from it with
    ``hydra.initialize_config_dir(str(rgns.config_dir()))``, or add it to an app's search path
    as ``pkg://rgns.conf``."""
    return (Path(__file__).parent / "conf").resolve()
