"""Forward model (multi-scale CNN + attention + LSTM), offline training, MAML online learning, and
the learner node.
"""
