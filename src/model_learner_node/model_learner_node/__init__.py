"""Offline training of the forward model (:mod:`peel_model`), MAML online learning, the replay
pool, the held-out gate and the learner node.
"""
