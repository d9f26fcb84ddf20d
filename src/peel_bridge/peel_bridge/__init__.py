"""peel_bridge: the one core both plant bridges (``peel_sim_node``, ``peel_nachi_bridge``) run.

* :mod:`.loop` -- the ROS-free task loop: which task runs when (readers ready, the learner's
  model between tasks), and the ROS time of a task's sample.
* :mod:`.plant_node` -- the rclpy side both bridge nodes share: the publishers, the command
  subscription, model following (``/peel/model_info``, ``/peel/model_update``) and per-sample
  publishing (the only module here that imports ROS).
"""
