"""Learning from demonstration with tactile features: Gaussian HMM (Baum-Welch) and GMR with
forward-variable weights (thesis ch. 5)."""
