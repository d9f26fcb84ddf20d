"""peel_nachi_bridge: the bridge to the Nachi robot controller (the emulator: :mod:`peel_nachi_emulator`).

* :mod:`.protocol` -- NACHI-PEEL 1 (docs/nachi_protocol.md): line grammar, strict parsing.
* :mod:`.link` -- one TCP connection (handshake, line reading) and the reconnect backoff.
* :mod:`.bridge` -- the ROS-free bridge core: task state machine and the link's safety rules.
* :mod:`.config` -- the bridge's parameters (config/peel_nachi_bridge.yaml), validated.
* :mod:`.node` -- the thin rclpy node (the only module here that imports ROS), on
  :mod:`peel_bridge` (the task loop and the topics both plant bridges share).
"""
