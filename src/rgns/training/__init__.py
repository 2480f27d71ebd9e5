"""Training: the LightningModule, loss designs and rollouts used in validation."""
