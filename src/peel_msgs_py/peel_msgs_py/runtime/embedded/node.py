"""``Node`` of the embedded runtime: rclpy's Node API on Cyclone DDS.

Parameter overrides come, in increasing precedence, from ``--params-file`` files (sections
``/**`` and the node's name), ``-p name:=value`` of the global (``rclpy.init(args=...)``) and
node (``cli_args``) ROS arguments, then ``parameter_overrides``. Every node declares
``use_sim_time`` (false); true makes its ROS clock follow ``/clock``. The standard parameter
services ``~/set_parameters``, ``~/get_parameters``, ``~/list_parameters`` and
``~/describe_parameters`` are served over DDS, and changes are published on
``/parameter_events``.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Callable, Sequence
from typing import Any

from ...errors import ParameterError, PeelError
from ...params import load_param_file
from . import args as ros_args
from .context import Context, NotInitializedException, get_default_context
from .entities import Publisher, Subscription, Timer, check_message_class
from .logging import RcutilsLogger
from .messages import (
    Clock as ClockMsg,
)
from .messages import (
    DescribeParameters,
    GetParameters,
    ListParameters,
    ListParametersResult,
    ParameterDescriptor,
    ParameterEvent,
    ParameterType,
    ParameterValue,
    SetParameters,
    SetParametersResult,
)
from .names import expand_topic_name, normalize_namespace, validate_node_name
from .parameter import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    NoParameterOverrideProvidedException,
    Parameter,
    ParameterAlreadyDeclaredException,
    ParameterImmutableException,
    ParameterNotDeclaredException,
    accepted,
    check_against_descriptor,
    refused,
)
from .qos import (
    QoSProfile,
    ReliabilityPolicy,
    as_profile,
    qos_profile_parameter_events,
    qos_profile_services_default,
)
from .services import Client, Service
from .time import Clock, ClockType, ROSClock

OnSetCallback = Callable[[list[Parameter]], SetParametersResult]
_uids = itertools.count(1)


class Node:
    """``rclpy.node.Node`` (the subset listed in docs/runtime.md)."""

    def __init__(
        self,
        node_name: str,
        *,
        context: Context | None = None,
        cli_args: Sequence[str] | None = None,
        namespace: str | None = None,
        use_global_arguments: bool = True,
        enable_rosout: bool = True,
        start_parameter_services: bool = True,
        parameter_overrides: Sequence[Parameter] | None = None,
        allow_undeclared_parameters: bool = False,
        automatically_declare_parameters_from_overrides: bool = False,
        **_ignored: Any,
    ) -> None:
        self.context = context or get_default_context()
        if not self.context.ok():
            raise NotInitializedException("rclpy.init() has not been called")
        global_args = self.context.ros_args if use_global_arguments else ros_args.RosArgs()
        local_args, _ = ros_args.parse(list(cli_args or []))
        name, ns = node_name, namespace
        for args in (global_args, local_args):
            for node, src, dst in args.remaps:
                if node not in (None, node_name):
                    continue
                if src == "__node" or src == "__name":
                    name = dst
                elif src == "__ns":
                    ns = dst
        self._name = validate_node_name(name)
        self._namespace = normalize_namespace(ns)
        self._remaps: dict[str, str] = {}
        for args in (global_args, local_args):
            for node, src, dst in args.remaps:
                if node in (None, node_name, self._name) and not src.startswith("__"):
                    self._remaps[self._expand(src, remap=False)] = self._expand(dst, remap=False)
        self._logger = RcutilsLogger(self._name)
        self._clock = ROSClock()
        self._publishers: list[Publisher] = []
        self._subscriptions: list[Subscription] = []
        self._timers: list[Timer] = []
        self._services: list[Service] = []
        self._clients: list[Client] = []
        self._uid = next(_uids)  # identifies the node in executors' wait-set cache
        self.version = 0  # bumped when entities change (executors rebuild their wait sets)
        self._executor: Any = None
        self._destroyed = False

        # ---- parameters
        self._parameters: dict[str, Parameter] = {}
        self._descriptors: dict[str, ParameterDescriptor] = {}
        self._allow_undeclared = allow_undeclared_parameters
        self._on_set: list[OnSetCallback] = []
        self._post_set: list[Callable[[list[Parameter]], None]] = []
        self._overrides = self._collect_overrides(global_args, local_args, parameter_overrides)
        self._param_events = (
            self.create_publisher(ParameterEvent, "/parameter_events", qos_profile_parameter_events)
            if enable_rosout or start_parameter_services
            else None
        )
        self._clock_sub: Subscription | None = None
        self.declare_parameter("use_sim_time", False)
        self._apply_use_sim_time(self.get_parameter("use_sim_time").value)
        if automatically_declare_parameters_from_overrides:
            for pname, param in self._overrides.items():
                if pname not in self._parameters:
                    self.declare_parameter(pname, param.value)
        if start_parameter_services:
            self._start_parameter_services()

    # ------------------------------------------------------------------ names
    def get_name(self) -> str:
        return self._name

    def get_namespace(self) -> str:
        return self._namespace

    def get_fully_qualified_name(self) -> str:
        return (self._namespace.rstrip("/") + "/" + self._name) if self._namespace != "/" else (
            "/" + self._name
        )

    def _expand(self, topic: str, remap: bool = True) -> str:
        full = expand_topic_name(topic, self._name, self._namespace)
        return self._remaps.get(full, full) if remap else full

    def resolve_topic_name(self, topic: str, *, only_expand: bool = False) -> str:
        return self._expand(topic, remap=not only_expand)

    def get_logger(self) -> RcutilsLogger:
        return self._logger

    def get_clock(self) -> Clock:
        return self._clock

    @property
    def executor(self) -> Any:
        return self._executor

    # ------------------------------------------------------------------ entities
    def _check_alive(self) -> None:
        if self._destroyed:
            raise PeelError(f"node {self._name} has been destroyed")

    def _add(self, bucket: list[Any], entity: Any) -> Any:
        bucket.append(entity)
        self.version += 1
        if not isinstance(entity, Timer):
            self.context.graph_changed(self)
        return entity

    def create_publisher(
        self, msg_type: type[Any], topic: str, qos_profile: QoSProfile | int, **_kw: Any
    ) -> Publisher:
        self._check_alive()
        check_message_class(msg_type)
        pub = Publisher(self, msg_type, self._expand(topic), as_profile(qos_profile))
        return self._add(self._publishers, pub)

    def create_subscription(
        self,
        msg_type: type[Any],
        topic: str,
        callback: Callable[[Any], Any],
        qos_profile: QoSProfile | int,
        *,
        raw: bool = False,
        **_kw: Any,
    ) -> Subscription:
        self._check_alive()
        check_message_class(msg_type)
        sub = Subscription(self, msg_type, self._expand(topic), callback, as_profile(qos_profile), raw)
        return self._add(self._subscriptions, sub)

    def create_timer(
        self,
        timer_period_sec: float,
        callback: Callable[[], Any] | None,
        callback_group: Any = None,
        clock: Clock | None = None,
        autostart: bool = True,
    ) -> Timer:
        self._check_alive()
        period_ns = round(float(timer_period_sec) * 1e9)
        timer = Timer(callback, period_ns, clock or self._clock, self, autostart)
        return self._add(self._timers, timer)

    def create_rate(self, frequency: float, clock: Clock | None = None) -> Any:
        raise PeelError("create_rate is not provided by the embedded runtime; use a timer")

    def create_service(
        self,
        srv_type: type[Any],
        srv_name: str,
        callback: Callable[[Any, Any], Any],
        *,
        qos_profile: QoSProfile = qos_profile_services_default,
        **_kw: Any,
    ) -> Service:
        self._check_alive()
        srv = Service(self, srv_type, self._expand(srv_name), callback, as_profile(qos_profile))
        return self._add(self._services, srv)

    def create_client(
        self,
        srv_type: type[Any],
        srv_name: str,
        *,
        qos_profile: QoSProfile = qos_profile_services_default,
        **_kw: Any,
    ) -> Client:
        self._check_alive()
        cli = Client(self, srv_type, self._expand(srv_name), as_profile(qos_profile))
        return self._add(self._clients, cli)

    def _destroy_entity(self, entity: Any) -> None:
        for bucket in (
            self._publishers,
            self._subscriptions,
            self._timers,
            self._services,
            self._clients,
        ):
            if entity in bucket:
                bucket.remove(entity)
                self.version += 1
                entity._delete()
                if not isinstance(entity, Timer):
                    self.context.graph_changed(self)
                return

    def destroy_publisher(self, publisher: Publisher) -> bool:
        self._destroy_entity(publisher)
        return True

    def destroy_subscription(self, subscription: Subscription) -> bool:
        self._destroy_entity(subscription)
        return True

    def destroy_timer(self, timer: Timer) -> bool:
        self._destroy_entity(timer)
        return True

    def destroy_service(self, service: Service) -> bool:
        self._destroy_entity(service)
        return True

    def destroy_client(self, client: Client) -> bool:
        self._destroy_entity(client)
        return True

    def destroy_node(self) -> bool:
        if self._destroyed:
            return True
        if self._executor is not None:
            with contextlib.suppress(Exception):
                self._executor.remove_node(self)
        for bucket in (
            self._timers,
            self._subscriptions,
            self._clients,
            self._services,
            self._publishers,
        ):
            for entity in list(bucket):
                if self.context._participant is not None:
                    entity._delete()
            bucket.clear()
        self.version += 1
        self._destroyed = True
        self.context.graph_changed(self, alive=False)
        return True

    @property
    def publishers(self) -> list[Publisher]:
        return list(self._publishers)

    @property
    def subscriptions(self) -> list[Subscription]:
        return list(self._subscriptions)

    @property
    def timers(self) -> list[Timer]:
        return list(self._timers)

    @property
    def services(self) -> list[Service]:
        return list(self._services)

    @property
    def clients(self) -> list[Client]:
        return list(self._clients)

    def count_publishers(self, topic_name: str) -> int:
        """Matched remote writers seen by this node's own subscriptions on that topic."""
        full = self._expand(topic_name)
        return sum(s.get_publisher_count() for s in self._subscriptions if s.topic == full)

    def count_subscribers(self, topic_name: str) -> int:
        """Matched remote readers seen by this node's own publishers on that topic."""
        full = self._expand(topic_name)
        return sum(p.get_subscription_count() for p in self._publishers if p.topic == full)

    # ------------------------------------------------------------------ sim time
    def _apply_use_sim_time(self, on: bool) -> None:
        if on and self._clock_sub is None:
            self._clock._set_ros_time_override_active(True)
            qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
            self._clock_sub = self.create_subscription(ClockMsg, "/clock", self._on_clock, qos)
        elif not on and self._clock_sub is not None:
            self._clock._set_ros_time_override_active(False)
            self._destroy_entity(self._clock_sub)
            self._clock_sub = None

    def _on_clock(self, msg: Any) -> None:
        self._clock._set_sim_time(msg.clock.sec * 1_000_000_000 + msg.clock.nanosec)

    # ------------------------------------------------------------------ parameters
    def _collect_overrides(
        self,
        global_args: ros_args.RosArgs,
        local_args: ros_args.RosArgs,
        extra: Sequence[Parameter] | None,
    ) -> dict[str, Parameter]:
        values: dict[str, Any] = {}
        key = self.get_fully_qualified_name().lstrip("/")
        for args in (global_args, local_args):
            for path in args.params_files:
                values.update(load_param_file(path, key))
        for args in (global_args, local_args):
            for node, pname, value in args.params:
                if node in (None, self._name):
                    values[pname] = value
        out: dict[str, Parameter] = {}
        for pname, value in values.items():
            try:
                out[pname] = Parameter(pname, value=value)
            except (TypeError, ValueError):
                raise ParameterError(
                    f"parameter '{pname}' has an unsupported value {value!r} "
                    "(lists must hold one type)"
                ) from None
        for p in extra or ():
            out[p.name] = p
        return out

    def declare_parameter(
        self,
        name: str,
        value: Any = None,
        descriptor: ParameterDescriptor | None = None,
        ignore_override: bool = False,
    ) -> Parameter:
        """Declare ``name`` with a default (or a ``Parameter.Type``); an override wins."""
        if name in self._parameters:
            raise ParameterAlreadyDeclaredException(name)
        descriptor = descriptor if descriptor is not None else ParameterDescriptor()
        descriptor.name = name
        if isinstance(value, Parameter.Type):
            ptype, value = value, None
        else:
            try:
                ptype = Parameter.Type.from_parameter_value(value)
            except TypeError:
                raise InvalidParameterTypeException(
                    f"parameter '{name}': default {value!r} has an unsupported type"
                ) from None
        if not descriptor.dynamic_typing and ptype is not Parameter.Type.NOT_SET:
            descriptor.type = ptype.value
        if not ignore_override and name in self._overrides:
            param = self._overrides[name]
        else:
            param = Parameter(name, value=value)
        if param.type_ is Parameter.Type.NOT_SET and descriptor.type != 0 and not (
            descriptor.dynamic_typing
        ):
            raise NoParameterOverrideProvidedException(name)
        reason = check_against_descriptor(param, descriptor)
        if reason is not None:
            exc = InvalidParameterTypeException if "wrong parameter type" in reason else (
                InvalidParameterValueException
            )
            raise exc(reason)
        result = self._run_on_set([param])
        if not result.successful:
            raise InvalidParameterValueException(
                f"parameter '{name}' = {param.value!r} refused: {result.reason}"
            )
        self._parameters[name] = param
        self._descriptors[name] = descriptor
        self._publish_event(new=[param])
        for cb in list(self._post_set):
            cb([param])
        return param

    def declare_parameters(
        self,
        namespace: str,
        parameters: Sequence[tuple[Any, ...]],
        ignore_override: bool = False,
    ) -> list[Parameter]:
        out = []
        for entry in parameters:
            pname = f"{namespace}.{entry[0]}" if namespace else entry[0]
            value = entry[1] if len(entry) > 1 else None
            desc = entry[2] if len(entry) > 2 else None
            out.append(self.declare_parameter(pname, value, desc, ignore_override))
        return out

    def undeclare_parameter(self, name: str) -> None:
        if name not in self._parameters:
            raise ParameterNotDeclaredException(name)
        if self._descriptors[name].read_only:
            raise ParameterImmutableException(f"parameter '{name}' is read-only")
        param = self._parameters.pop(name)
        self._descriptors.pop(name)
        self._publish_event(deleted=[param])

    def has_parameter(self, name: str) -> bool:
        return name in self._parameters

    def get_parameter(self, name: str) -> Parameter:
        if name in self._parameters:
            return self._parameters[name]
        if self._allow_undeclared:
            return Parameter(name, Parameter.Type.NOT_SET, None)
        raise ParameterNotDeclaredException(name)

    def get_parameter_or(self, name: str, alternative_value: Parameter | None = None) -> Parameter:
        if alternative_value is None:
            alternative_value = Parameter(name, Parameter.Type.NOT_SET)
        return self._parameters.get(name, alternative_value)

    def get_parameters(self, names: Sequence[str]) -> list[Parameter]:
        return [self.get_parameter(n) for n in names]

    def get_parameters_by_prefix(self, prefix: str) -> dict[str, Parameter]:
        pre = prefix + "." if prefix else ""
        return {n[len(pre):]: p for n, p in self._parameters.items() if n.startswith(pre)}

    def describe_parameter(self, name: str) -> ParameterDescriptor:
        if name not in self._descriptors:
            raise ParameterNotDeclaredException(name)
        return self._descriptors[name]

    def describe_parameters(self, names: Sequence[str]) -> list[ParameterDescriptor]:
        return [self.describe_parameter(n) for n in names]

    def add_on_set_parameters_callback(self, callback: OnSetCallback) -> OnSetCallback:
        """``callback(list[Parameter]) -> SetParametersResult``; refusing keeps old values."""
        self._on_set.insert(0, callback)
        return callback

    def remove_on_set_parameters_callback(self, callback: OnSetCallback) -> None:
        self._on_set.remove(callback)

    def add_post_set_parameters_callback(
        self, callback: Callable[[list[Parameter]], None]
    ) -> Callable[[list[Parameter]], None]:
        self._post_set.append(callback)
        return callback

    def _run_on_set(self, params: list[Parameter]) -> SetParametersResult:
        for cb in list(self._on_set):
            result = cb(params)
            if not isinstance(result, SetParametersResult):
                return refused(f"on-set callback {cb!r} returned {type(result).__name__}")
            if not result.successful:
                return result
        return accepted()

    def set_parameters(self, parameter_list: Sequence[Parameter]) -> list[SetParametersResult]:
        """Set each parameter on its own (rclpy semantics); one result per parameter."""
        return [self.set_parameters_atomically([p]) for p in parameter_list]

    def set_parameters_atomically(self, parameter_list: Sequence[Parameter]) -> SetParametersResult:
        params = list(parameter_list)
        new: list[Parameter] = []
        for p in params:
            if not isinstance(p, Parameter):
                raise TypeError(f"expected Parameter, got {type(p).__name__}")
            if p.name not in self._parameters:
                if not self._allow_undeclared:
                    raise ParameterNotDeclaredException(p.name)
                new.append(p)
                continue
            desc = self._descriptors[p.name]
            if desc.read_only:
                return refused(f"parameter '{p.name}' is read-only")
            if p.type_ is Parameter.Type.NOT_SET:
                return refused(f"parameter '{p.name}': cannot unset a declared parameter")
            reason = check_against_descriptor(p, desc)
            if reason is not None:
                return refused(reason)
        result = self._run_on_set(params)
        if not result.successful:
            return result
        changed = [p for p in params if p not in new]
        for p in params:
            self._parameters[p.name] = p
            if p in new:
                self._descriptors[p.name] = ParameterDescriptor(
                    name=p.name, type=p.type_.value, dynamic_typing=True
                )
        self._publish_event(new=new, changed=changed)
        for cb in list(self._post_set):
            cb(params)
        if any(p.name == "use_sim_time" for p in params):
            self._apply_use_sim_time(bool(self._parameters["use_sim_time"].value))
        return result

    def _publish_event(self, new=(), changed=(), deleted=()) -> None:
        if self._param_events is None:
            return
        ev = ParameterEvent(
            stamp=self._clock.now().to_msg(),
            node=self.get_fully_qualified_name(),
            new_parameters=[p.to_parameter_msg() for p in new],
            changed_parameters=[p.to_parameter_msg() for p in changed],
            deleted_parameters=[p.to_parameter_msg() for p in deleted],
        )
        with contextlib.suppress(Exception):
            self._param_events.publish(ev)

    # --- the standard parameter services
    def _start_parameter_services(self) -> None:
        self.create_service(SetParameters, "~/set_parameters", self._srv_set)
        self.create_service(GetParameters, "~/get_parameters", self._srv_get)
        self.create_service(ListParameters, "~/list_parameters", self._srv_list)
        self.create_service(DescribeParameters, "~/describe_parameters", self._srv_describe)

    def _srv_set(self, request: Any, response: Any) -> Any:
        for msg in request.parameters:
            try:
                param = Parameter.from_parameter_msg(msg)
                result = self.set_parameters_atomically([param])
            except (PeelError, TypeError, ValueError) as exc:
                result = refused(str(exc))
            response.results.append(result)
        return response

    def _srv_get(self, request: Any, response: Any) -> Any:
        for name in request.names:
            p = self._parameters.get(name)
            response.values.append(
                p.get_parameter_value() if p is not None else ParameterValue(type=0)
            )
        return response

    def _srv_list(self, request: Any, response: Any) -> Any:
        names, prefixes = [], set()
        for name in sorted(self._parameters):
            if request.prefixes and not any(
                name == pre or name.startswith(pre + ".") for pre in request.prefixes
            ):
                continue
            depth = name.count(".") + 1
            if request.depth and depth > request.depth:
                continue
            names.append(name)
            if "." in name:
                prefixes.add(name.rsplit(".", 1)[0])
        response.result = ListParametersResult(names=names, prefixes=sorted(prefixes))
        return response

    def _srv_describe(self, request: Any, response: Any) -> Any:
        for name in request.names:
            desc = self._descriptors.get(name)
            response.descriptors.append(
                desc if desc is not None else ParameterDescriptor(name=name, type=0)
            )
        return response


__all__ = ["ClockType", "Node", "ParameterType"]
