"""Interface contract of peel: topic names, QoS, message classes mirroring Jazzy, trajectory
codec, SI/paper unit conversion, parameter loading, the embedded DDS runtime and the MCAP
recorder.
"""
