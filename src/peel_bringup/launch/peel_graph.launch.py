"""``ros2 launch peel_bringup peel_graph.launch.py``: the peel node graph for ROS 2 Jazzy users.

The same graph as ``peel graph`` (docs/graph.md), with ROS 2 launch instead of the launcher:

    ros2 launch peel_bringup peel_graph.launch.py plant:=plant tasks:=3 seed:=0 \\
        params:=/path/override.yaml record:=/path/bag out:=runs/launch
    ros2 launch peel_bringup peel_graph.launch.py plant:=nachi nachi_host:=192.168.0.20 \\
        nachi_port:=48100 tasks:=3
    ros2 launch peel_bringup peel_graph.launch.py live:=8765    # + the Foxglove live view

* ``plant:=nachi`` starts the bridge to the Nachi robot controller (``peel_nachi_bridge``,
  docs/nachi.md) in the simulator's place, at ``nachi_host:nachi_port`` (empty: the
  ``link.host`` / ``link.port`` of its config file); the substrates are the robot's, ``seed``
  goes to the planner only;
* every node gets ``share/peel_bringup/config/<node>.yaml``, then the override file (if any),
  then ``use_sim_time: true`` and the settings below;
* the planner and the bridge are managed nodes started unconfigured (``node.autostart: false``);
  our lifecycle manager (``peel lifecycle up``, node ``peel_lifecycle_manager``) configures both,
  then activates the planner, then the bridge, through their ``change_state`` services, and
  exits; a configure that fails (the node stays unconfigured, its log says why) or a node that
  does not answer within ``graph.lifecycle_timeout_s`` makes it exit 1, which shuts the launch
  down;
* ``live:=PORT`` adds the live view (``peel live``, node ``peel_live``: the running graph on a
  Foxglove WebSocket at ``ws://live_host:PORT``, ``live_host`` default 127.0.0.1, as
  ``peel graph --live PORT``); it counts among the readers the bridge and the planner wait for;
* ``record:=BAG`` adds the recorder (``ros2 run peel_bag peel_recorder --out BAG``, the
  same as ``peel record``; ``ros2 bag record -s mcap`` works too, the bag layout is the same);
* ``namespace:=/cell_a`` puts the three nodes under ``/cell_a``: every topic
  (``/cell_a/peel/wrench``, ``/cell_a/clock``, ...) and the planner's services move with them
  (docs/fleet.md); the recorder records the root cell only, so ``record:=`` needs an empty
  namespace (``peel fleet --record`` records each cell);
* the simulator (or the bridge) exits after the K tasks and the learner's last swap
  (``node.exit_when_done``); its exit, or any node's death, shuts the whole launch down (the
  recorder closes its bag on the SIGINT that launch sends).
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
NACHI = "peel_nachi_bridge"
#: The nodes our lifecycle manager brings up, in the order they are activated (the bridge last).
MANAGED = ("peel_planner_node",)
MANAGER = "peel_lifecycle_manager"
LIVE = "peel_live"


def _tools(arg: dict) -> int:
    """Readers besides the graph's own that the bridge and the planner wait for."""
    return int(bool(arg["record"])) + int(bool(arg["live"]))


def _bridge(arg: dict) -> tuple[str, dict]:
    """The node that publishes the state (simulator or Nachi bridge) and its settings."""
    readers = {"node.min_subscribers": 1 + _tools(arg),
               "node.min_traj_subscribers": 1 + _tools(arg)}
    common = {"node.tasks": int(arg["tasks"]), "node.exit_when_done": True,
              "node.autostart": False, **readers}
    if arg["plant"] != "nachi":
        return "peel_sim_node", {"node.source": arg["plant"], "node.seed": int(arg["seed"]),
                                 **common}
    link = {}
    if arg["nachi_host"]:
        link["link.host"] = arg["nachi_host"]
    if arg["nachi_port"]:
        link["link.port"] = int(arg["nachi_port"])
    return NACHI, {**common, **link}


def _setup(context, *args, **kwargs):
    cfg = os.path.join(get_package_share_directory("peel_bringup"), "config")
    arg = {name: context.launch_configurations[name] for name in (
        "plant", "tasks", "seed", "params", "record", "out", "nachi_host", "nachi_port", "live",
        "live_host", "namespace")}
    namespace = arg["namespace"].rstrip("/")
    if namespace and (arg["record"] or arg["live"]):
        raise RuntimeError("record:= and live:= serve the root cell only; leave namespace:= "
                           "empty, or record each cell with: peel fleet --record BAG")
    override = [arg["params"]] if arg["params"] else []
    models = os.path.abspath(os.path.join(arg["out"], "models"))
    bridge, settings = _bridge(arg)
    settings["node.learner_node"] = f"{namespace}/model_learner_node"  # the producer it waits for
    extra = {
        bridge: settings,
        "peel_planner_node": {"node.seed": int(arg["seed"]), "node.autostart": False,
                              "node.min_cmd_subscribers": 1 + _tools(arg)},
        "model_learner_node": {"node.out_dir": models},
    }
    actions = []
    nodes = {}
    for name in (bridge, *NODES[1:]):
        nodes[name] = Node(
            package=name, executable=name, name=name, output="screen",
            namespace=namespace or None,
            parameters=[os.path.join(cfg, f"{name}.yaml"), *override,
                        {"use_sim_time": True, **extra[name]}],
        )
        actions.append(nodes[name])
    actions += _manager([f"{namespace}/{n}" if namespace else n for n in (*MANAGED, bridge)])
    if arg["live"]:
        actions.insert(0, _live(arg, override))
    if arg["record"]:
        actions.insert(0, Node(package="peel_bag", executable="peel_recorder",
                               name="peel_recorder", output="screen", sigterm_timeout="20",
                               arguments=["--out", arg["record"]]))
    # the simulator or the bridge finishing (or any node dying) ends the launch
    for name in nodes:
        actions.append(RegisterEventHandler(OnProcessExit(
            target_action=nodes[name],
            on_exit=[EmitEvent(event=Shutdown(reason=f"{name} exited"))])))
    return actions


def _manager(managed: list[str]) -> list:
    """``peel lifecycle up`` of the managed nodes; its failure ends the launch."""
    manager = Node(package="peel_bringup", executable="peel", name=MANAGER, output="screen",
                   arguments=["lifecycle", "up", *managed])

    def failed(event, context):
        if event.returncode != 0:
            return [EmitEvent(event=Shutdown(reason=f"{MANAGER}: the managed nodes did not "
                                                    f"come up (exit {event.returncode})"))]
        return []

    return [manager, RegisterEventHandler(OnProcessExit(target_action=manager, on_exit=failed))]


def _live(arg: dict, override: list[str]) -> Node:
    """``peel live --port PORT --host HOST [--params FILE]``: the Foxglove live view."""
    extra = ["--params", os.path.abspath(override[0])] if override else []
    return Node(package="peel_bringup", executable="peel", name=LIVE, output="screen",
                arguments=["live", "--port", str(int(arg["live"])), "--host", arg["live_host"],
                           *extra])


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("plant", default_value="sim", choices=["sim", "plant", "nachi"],
                              description="run the tasks on the simulator, the plant or the "
                                          "Nachi robot controller"),
        DeclareLaunchArgument("nachi_host", default_value="",
                              description="controller address for plant:=nachi (empty: "
                                          "link.host of config/peel_nachi_bridge.yaml)"),
        DeclareLaunchArgument("nachi_port", default_value="",
                              description="controller TCP port for plant:=nachi (empty: "
                                          "link.port)"),
        DeclareLaunchArgument("tasks", default_value="3", description="consecutive tasks K"),
        DeclareLaunchArgument("seed", default_value="0", description="task sequence seed"),
        DeclareLaunchArgument("params", default_value="",
                              description="ROS 2 parameter file applied on top of config/"),
        DeclareLaunchArgument("record", default_value="",
                              description="bag directory to record to (empty: no bag)"),
        DeclareLaunchArgument("out", default_value="runs/launch",
                              description="directory for the learner's model_vNNNN files"),
        DeclareLaunchArgument("live", default_value="",
                              description="port of the Foxglove live view, as peel graph --live "
                                          "PORT (empty: no live view; 8765 is Foxglove's)"),
        DeclareLaunchArgument("live_host", default_value="127.0.0.1",
                              description="address the live view binds (default: this machine "
                                          "only)"),
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the cell's nodes and topics, e.g. "
                                          "/cell_a (empty: the root, /peel/...)"),
        OpaqueFunction(function=_setup),
    ])
