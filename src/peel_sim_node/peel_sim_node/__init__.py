"""PyBullet glass-peeling simulator, reality-gap plant, dataset generation, and the simulator
bridge node.
"""
