"""Particle types, as DeepMind's datasets number them: the solvers simulate them, the data
contract (:mod:`rgns.data.contract`) stores them, the models embed them."""

RIGID, KINEMATIC, WATER, SAND, GOOP = 0, 3, 5, 6, 7
NUM_PARTICLE_TYPES = 9  # the width of the models' type embedding table
