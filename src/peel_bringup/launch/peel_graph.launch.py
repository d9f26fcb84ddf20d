"""``ros2 launch peel_bringup peel_graph.launch.py``: the peel node graph for ROS 2 Jazzy users.

The same graph as ``peel graph`` (docs/graph.md), with ROS 2 launch instead of the launcher:

    ros2 launch peel_bringup peel_graph.launch.py plant:=plant tasks:=3 seed:=0 \\
        params:=/path/override.yaml record:=/path/bag out:=runs/launch

* every node gets ``share/peel_bringup/config/<node>.yaml``, then the override file (if any),
  then ``use_sim_time: true`` and the settings below;
* ``record:=BAG`` adds the recorder (``ros2 run peel_msgs_py peel_recorder --out BAG``, the
  same as ``peel record``; ``ros2 bag record -s mcap`` works too, the bag layout is the same);
* the simulator exits after the K tasks and the learner's last swap (``node.exit_when_done``);
  its exit, or any node's death, shuts the whole launch down (the recorder closes its bag on
  the SIGINT that launch sends).
"""

from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch_ros.actions import Node

NODES = ("peel_sim_node", "peel_planner_node", "model_learner_node")


def _setup(context, *args, **kwargs):
    cfg = os.path.join(get_package_share_directory("peel_bringup"), "config")
    arg = {name: context.launch_configurations[name]
           for name in ("plant", "tasks", "seed", "params", "record", "out")}
    override = [arg["params"]] if arg["params"] else []
    models = os.path.abspath(os.path.join(arg["out"], "models"))
    extra = {
        "peel_sim_node": {"node.source": arg["plant"], "node.tasks": int(arg["tasks"]),
                          "node.seed": int(arg["seed"]), "node.exit_when_done": True,
                          "node.min_subscribers": 2 if arg["record"] else 1,
                          "node.min_traj_subscribers": 2 if arg["record"] else 1},
        "peel_planner_node": {"node.seed": int(arg["seed"]),
                              "node.min_cmd_subscribers": 2 if arg["record"] else 1},
        "model_learner_node": {"node.out_dir": models},
    }
    actions = []
    nodes = {}
    for name in NODES:
        nodes[name] = Node(
            package=name, executable=name, name=name, output="screen",
            parameters=[os.path.join(cfg, f"{name}.yaml"), *override,
                        {"use_sim_time": True, **extra[name]}],
        )
        actions.append(nodes[name])
    if arg["record"]:
        actions.insert(0, Node(package="peel_msgs_py", executable="peel_recorder",
                               name="peel_recorder", output="screen", sigterm_timeout="20",
                               arguments=["--out", arg["record"]]))
    # the simulator finishing (or any node dying) ends the launch
    for name in NODES:
        actions.append(RegisterEventHandler(OnProcessExit(
            target_action=nodes[name],
            on_exit=[EmitEvent(event=Shutdown(reason=f"{name} exited"))])))
    return actions


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("plant", default_value="sim", choices=["sim", "plant"],
                              description="run the tasks on the simulator or the plant"),
        DeclareLaunchArgument("tasks", default_value="3", description="consecutive tasks K"),
        DeclareLaunchArgument("seed", default_value="0", description="task sequence seed"),
        DeclareLaunchArgument("params", default_value="",
                              description="ROS 2 parameter file applied on top of config/"),
        DeclareLaunchArgument("record", default_value="",
                              description="bag directory to record to (empty: no bag)"),
        DeclareLaunchArgument("out", default_value="runs/launch",
                              description="directory for the learner's model_vNNNN files"),
        OpaqueFunction(function=_setup),
    ])
