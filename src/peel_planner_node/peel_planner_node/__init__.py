"""OL-MPPI planner library and the planner node."""
