"""Errors every layer may raise for a bad option (the other refusals live beside what they check:
``DatasetError`` in :mod:`rgns.data.contract`, ``CheckpointError`` in
:mod:`rgns.training.module`, ``UnsafeConfigError`` in :mod:`rgns.targets`)."""


class ConfigError(ValueError):
    """An option has a value rgns cannot use; the message names the key (``model.layers``)."""
