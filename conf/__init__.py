"""The Hydra configs, a package so that Hydra finds them as ``pkg://rgns.conf`` once installed."""
