"""PyG layers of the GNS family: the interaction network, the reversible coupling and its
stack (RRMP), and the encoders/decoders between physical and latent node features."""
from rgns.nn.interaction import InteractionNetwork
from rgns.nn.mlp import mlp
from rgns.nn.projection import ILP, MLPEncoderDecoder
from rgns.nn.reversible import RRMP, Coupling

__all__ = ["ILP", "MLPEncoderDecoder", "InteractionNetwork", "Coupling", "RRMP", "mlp"]
