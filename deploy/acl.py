"""Zenoh access-control rules for an Argus site, one principal (login) per process.

Pure: :func:`access_control` turns a list of :class:`Principal` into the ``access_control`` block
of a Zenoh 1.x router config (``default_permission: "deny"``). What each role may do::

    edge-camera C   put cam/C/{frame,oracle}, status/edge-camera/C; token alive/edge-camera/C
    robot-agent R   put robot/R/{frame,oracle,state,viewpoints}, status/robot-agent/R; token alive/..;
                    receive robot/R/goal, answer it on robot/R/goal/status{,/json}; answer queries on
                    robot/R/viewpoints
    mapper          put/delete graph/**, map/**, its status; token; receive every cam/robot frame
                    and oracle; answer queries on graph/**; keyframe jobs: put work/job/*, receive
                    work/{ack,result}/*, answer work/keyframe/*/*, watch alive/worker/*; and the worker's
                    part below for each of its local workers (<mapper id>-local<i>: they log in as it)
    worker W        receive work/job/W; put work/{ack,result}/W, status/worker/W; token alive/worker/W;
                    query work/keyframe/*/* (source keyframes from the mapper's store)
    planner         put robot/*/goal, its status; token; receive graph/{snapshot,delta}, map/points,
                    robot/*/{state,viewpoints,goal/status{,/json}}; query graph/snapshot, robot/*/viewpoints;
                    watch alive/** (``argus goal`` on a secure site logs in as the planner)
    consumer        receive and query graph/** (read only)
    monitor         watch alive/** and receive status/** (the launcher's health view; read only)

Zenoh checks a *declaration* (subscriber, queryable) against the rules by inclusion: a subscriber on
``graph/**`` needs a rule on ``graph/**`` (or wider), so the rules below name the exact expressions the
processes declare. Every publishing role may *receive* subscriber declarations (egress
``declare_subscriber``) on ``argus/<site>/**``: a client only sends a put when its router has told it
that someone subscribes, so without that grant every put is dropped at the sender (issue 19: the
shipped ACL blocked the real edge camera that way). It tells a principal which key expressions are
subscribed, never any data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from protocol.keys import Keys, validate_id

Role = Literal["edge-camera", "robot-agent", "mapper", "planner", "worker", "consumer", "monitor"]
ROLES: tuple[Role, ...] = ("edge-camera", "robot-agent", "mapper", "planner", "worker", "consumer", "monitor")

Flow = Literal["ingress", "egress"]


@dataclass(frozen=True)
class Principal:
    """One login: ``user`` (user name, also the certificate common name), its role and node id; a mapper's
    ``local_workers`` (``[workers] local``) log in as it and get the worker's part for their ids."""

    user: str
    role: Role
    node_id: str
    local_workers: int = 0

    def __post_init__(self) -> None:
        validate_id(self.user, "user name")
        validate_id(self.node_id, "node id")
        if self.role not in ROLES:
            raise ValueError(f"unknown role {self.role!r} (one of {', '.join(ROLES)})")


@dataclass(frozen=True)
class Grant:
    """Messages allowed in one direction on some key expressions (ingress: from the principal)."""

    flow: Flow
    messages: tuple[str, ...]
    key_exprs: tuple[str, ...]


def _in(messages: str, *keys: str) -> Grant:
    return Grant("ingress", tuple(messages.split()), keys)


def _out(messages: str, *keys: str) -> Grant:
    return Grant("egress", tuple(messages.split()), keys)


def grants(p: Principal, keys: Keys) -> list[Grant]:
    """What principal ``p`` may do on the site of ``keys`` (everything else is denied)."""
    r, i = keys.root, p.node_id
    alive, status = keys.alive(p.role, i), keys.status(p.role, i)
    learn_subs = _out("declare_subscriber", f"{r}/**")  # see the module docstring
    presence = [_in("put", status), _in("liveliness_token", alive), learn_subs]
    if p.role == "edge-camera":
        return [_in("put", keys.cam_frame(i), keys.oracle("fixed", i)), *presence]
    if p.role == "robot-agent":
        return [
            _in("put", keys.robot_frame(i), keys.oracle("robot", i), keys.robot_state(i), keys.robot_viewpoints(i),
                keys.robot_goal_status(i), keys.robot_goal_status_json(i)),
            *presence,
            _in("declare_subscriber", keys.robot_goal(i)), _out("put", keys.robot_goal(i)),
            # The planner asks robot/*/viewpoints, and Zenoh checks the query's own (wildcard) key: each
            # robot sees every viewpoint query but may only answer with its own key.
            _in("declare_queryable reply", keys.robot_viewpoints(i)), _out("query", keys.all_robot_viewpoints),
        ]
    if p.role == "mapper":
        frames = [f"{r}/{kind}/*/{topic}" for kind in ("cam", "robot") for topic in ("frame", "oracle")]
        answers = (keys.all_work_acks, keys.all_work_results)
        local = [g for n in range(p.local_workers) for g in _worker(keys, f"{i}-local{n}")]
        return [
            _in("put delete", keys.graph_all, f"{r}/map/**"), *presence,
            _in("declare_subscriber", keys.all_frames, keys.all_oracle), _out("put", *frames),
            _in("declare_queryable reply", keys.graph_all), _out("query", keys.graph_all),
            _in("put", f"{r}/work/job/*"), _in("declare_subscriber", *answers), _out("put", *answers),
            _in("declare_queryable reply", keys.all_work_keyframes), _out("query", keys.all_work_keyframes),
            _in("declare_liveliness_subscriber liveliness_query", keys.all_alive_of("worker")),
            _out("liveliness_token", keys.all_alive_of("worker")), *local,
        ]
    if p.role == "worker":
        return [*_worker(keys, i), learn_subs]
    if p.role == "planner":
        reads = (keys.graph_snapshot, keys.graph_delta, keys.map_points, keys.all_robot_states,
                 keys.all_robot_viewpoints, f"{keys.all_robot_goals}/status", f"{keys.all_robot_goals}/status/json")
        asks = (keys.graph_snapshot, keys.all_robot_viewpoints)
        return [
            _in("put", f"{r}/robot/*/goal"), *presence,
            _in("declare_subscriber", *reads), _out("put", *reads),
            _in("query", *asks), _out("reply", *asks),
            _in("declare_liveliness_subscriber liveliness_query", keys.all_alive),
            _out("liveliness_token", keys.all_alive),
        ]
    if p.role == "consumer":
        return [_in("declare_subscriber query", keys.graph_all), _out("put delete reply", keys.graph_all)]
    # monitor
    return [
        _in("declare_liveliness_subscriber liveliness_query", keys.all_alive),
        _out("liveliness_token", keys.all_alive),
        _in("declare_subscriber", keys.all_status), _out("put", keys.all_status),
    ]


def _worker(keys: Keys, worker_id: str) -> list[Grant]:
    """What a keyframe worker does: its status and token, its jobs in, acks and results out, source
    keyframes fetched from the mapper's store (a query on the exact keyframe key)."""
    job = keys.work_job(worker_id)
    return [
        _in("put", keys.status("worker", worker_id), keys.work_ack(worker_id), keys.work_result(worker_id)),
        _in("liveliness_token", keys.alive("worker", worker_id)),
        _in("declare_subscriber", job), _out("put", job),
        _in("query", keys.all_work_keyframes), _out("reply", keys.all_work_keyframes),
    ]


def access_control(principals: list[Principal], site: str = "default", *, cert_names: bool = False) -> dict[str, Any]:
    """The ``access_control`` block of a router config: default deny, one subject per principal.

    ``cert_names``: a subject also needs the TLS client certificate whose common name is the user
    name (mutual TLS), so a stolen password alone does not log in.
    """
    users = [p.user for p in principals]
    dup = sorted({u for u in users if users.count(u) > 1})
    if dup:
        raise ValueError(f"duplicate user names: {dup}")
    keys = Keys(site)
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for p in principals:
        ids = []
        for n, g in enumerate(grants(p, keys)):
            rid = f"{p.user}/{n}"
            ids.append(rid)
            rules.append({"id": rid, "permission": "allow", "flows": [g.flow], "messages": list(g.messages),
                          "key_exprs": list(g.key_exprs)})
        subject: dict[str, Any] = {"id": p.user, "usernames": [p.user]}
        if cert_names:
            subject["cert_common_names"] = [p.user]
        subjects.append(subject)
        policies.append({"id": p.user, "rules": ids, "subjects": [p.user]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}
