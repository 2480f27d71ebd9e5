"""Data: the on-disk contract, graphs, windows, generation, conversion and the DataModule."""
