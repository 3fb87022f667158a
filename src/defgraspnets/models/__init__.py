"""Learned models: the DefGraspNets multigraph and MeshGraphNet, the tactile wrench CNN, and their LightningModules."""
