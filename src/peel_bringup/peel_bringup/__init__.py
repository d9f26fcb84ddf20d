"""The peel command, the graph launcher, the demo and the launch file."""
