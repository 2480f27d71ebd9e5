"""Simulators on the physical state: R-GNS, GNS and Sep-GNS, and the paper's other forward
baselines EGNN, NeuralSPH and DMCF (see :mod:`rgns.models.base` for the state and the two
directions)."""
from rgns.models.base import Simulator, State, count_parameters
from rgns.models.dmcf import DMCF
from rgns.models.egnn import EGNN
from rgns.models.gns import GNS
from rgns.models.neural_sph import NeuralSPH
from rgns.models.rgns import RGNS
from rgns.models.sep_gns import SepGNS

__all__ = ["DMCF", "EGNN", "GNS", "NeuralSPH", "RGNS", "SepGNS", "Simulator", "State", "count_parameters"]
