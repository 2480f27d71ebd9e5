"""rgns: the Reversible Graph Network Simulator and its experiment framework."""
__version__ = "0.1.0"
