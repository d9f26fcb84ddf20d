"""The forward model f_theta (multi-scale CNN + attention + LSTM, 3.1) and the baselines' models,
the predictor, the compensated model and its effect terms, the checkpoint format and its
validation, and the model versions the planner hands out.
"""
