"""The peel command, the graph launcher, the experiments and the launch file."""
