"""Fuzz campaign (hypothesis, derandomized) on every decoder a peer or a config file can reach.

Each target feeds generated input (random bytes, and mutations of valid input: truncations, byte flips,
lying sizes, wrong kinds and versions, hostile values) to one decoder and lets through only the error type
that decoder documents; anything else escaping is a bug (the test fails with the shrunk input).

Targets (decoder: the only error allowed out):
  jpeg         protocol.jpeg.decode_jpeg / jpeg_problem / jpeg_size: JpegError
  png          protocol.oracle.decode_u16_png / png_to_depth (ORACLE samples): JpegError
  envelope     protocol.codec.decode, every kind, major and minor, with and without an expected class: DecodeError
  frame        the mapper's frame handler (header attachment, key, JPEG, pose, intrinsics) then its decoder: nothing
  query        protocol.query.GraphQuery.from_parameters, then the mapper's graph query: ValueError
  toml         protocol.tomlconfig.load_config for every process config, file and --set overrides: ConfigError
  launch       deploy.up.load_launch: ValueError

The fast tier runs ``FAST_EXAMPLES`` per target; ``-m slow`` runs ``LONG_EXAMPLES`` per target (>= 10^5 in all)
and prints the count per target and the wall time.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from deploy.up import load_launch
from edge_camera.config import EdgeCameraConfig
from mapper.config import GeometryConfig, MapperConfig, PerceptionConfig
from mapper.core import MapperCore
from mapper.node import MapperNode
from planner.config import PlannerNodeConfig
from protocol.codec import MAGIC, REGISTRY, DecodeError, decode, encode
from protocol.jpeg import JpegError, decode_jpeg, encode_jpeg, jpeg_problem, jpeg_size
from protocol.keys import Keys
from protocol.messages import FrameHeader, Intrinsics
from protocol.oracle import decode_u16_png, encode_u16_png, png_to_depth
from protocol.query import GraphQuery
from protocol.tomlconfig import ConfigError, load_config
from protocol.wire import WIRE_MESSAGES
from robot_agent.config import RobotAgentConfig
from tests.support.boxes import EYES, INTR, oracle_core, view
from tests.support.strategies import ROOM_STRATEGIES
from tests.support.strategies import STRATEGIES as MESSAGE_STRATEGIES

FAST_EXAMPLES = 150
LONG_EXAMPLES = 15_000
KEYS = Keys("fuzz")

STRATEGIES = {**MESSAGE_STRATEGIES, **ROOM_STRATEGIES}  # every kind the codec decodes, the room layer's included

# --- shared strategies ---------------------------------------------------------------------------------
ints = st.one_of(st.integers(-(2**63), 2**64 - 1), st.sampled_from([0, -1, 1, 2**31, 2**53 + 1, 2**63 - 1]))
floats = st.floats(allow_nan=True, allow_infinity=True)
scalars = st.one_of(st.none(), st.booleans(), ints, floats, st.text(max_size=20), st.binary(max_size=20))


@st.composite
def ndarray_ext(draw: st.DrawFn) -> msgpack.ExtType:
    """The codec's array ext, honest or lying (dtype, shape, byte count, ext code)."""
    dtype = draw(st.sampled_from(["<f4", "<f8", "|u1", "<i8", "|b1", "<f2", "|O", ">f8", "<U4", "x", ""]))
    shape = draw(st.one_of(st.lists(st.integers(0, 6), max_size=3), st.lists(ints, max_size=9), scalars))
    try:
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize if isinstance(shape, list) else 0
    except (TypeError, ValueError, OverflowError):
        n = 0
    raw = draw(st.one_of(st.binary(min_size=max(0, min(n, 512)), max_size=max(0, min(n, 512))), st.binary(max_size=64),
                         scalars))
    inner = msgpack.packb(draw(st.sampled_from([[dtype, shape, raw], [dtype, shape], "x", [dtype, shape, raw, 1]])),
                          use_bin_type=True)
    return msgpack.ExtType(draw(st.sampled_from([1, 1, 1, 2, 127])), inner)


values = st.recursive(
    st.one_of(scalars, ndarray_ext()),
    lambda inner: st.one_of(st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=12), inner, max_size=5)),
    max_leaves=20,
)


def _pack(obj: Any) -> bytes:
    from protocol.codec import _default

    return msgpack.packb(obj, default=_default, use_bin_type=True)


@st.composite
def hostile_body(draw: st.DrawFn) -> tuple[str, dict[str, Any]]:
    """A valid message's field map with some fields replaced, removed or added."""
    cls = draw(st.sampled_from(WIRE_MESSAGES))
    body = dict(draw(STRATEGIES[cls]).model_dump(mode="python"))
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(["replace", "remove", "add"]))
        if op == "replace" and body:
            body[draw(st.sampled_from(sorted(body)))] = draw(values)
        elif op == "remove" and body:
            body.pop(draw(st.sampled_from(sorted(body))))
        else:
            body[draw(st.text(max_size=10))] = draw(values)
    return cls.KIND, body


@st.composite
def envelopes(draw: st.DrawFn, kind: str | None = None) -> bytes:
    """Envelopes of every kind, major and minor, honest or lying; mutated bytes; random bytes."""
    how = draw(st.sampled_from(["honest", "body", "layout", "bytes", "random"]))
    if how == "random":
        return draw(st.binary(max_size=256))
    k, body = draw(hostile_body())
    if kind is not None:
        k = kind
    if how == "honest":
        cls = REGISTRY[k]
        return encode(draw(STRATEGIES[cls]))
    major = draw(st.one_of(st.sampled_from([1, 1, 1, 0, 2]), ints))
    minor = draw(st.one_of(st.sampled_from([0, 1, 2, 99]), ints))
    kinds = st.one_of(st.just(k), st.sampled_from(sorted(REGISTRY)), st.text(max_size=12), scalars)
    env: Any = [MAGIC, draw(kinds) if how == "layout" else k, major, minor, body]
    if how == "layout":
        env = draw(st.sampled_from([env, env[:4], [*env, 1], {"a": env}, env[4], [draw(scalars), *env[1:]]]))
    data = _pack(env)
    if how == "bytes":
        data = draw(mutate(data))
    return data


@st.composite
def mutate(draw: st.DrawFn, data: bytes) -> bytes:
    """Truncations, byte flips, insertions and deletions of ``data``."""
    b = bytearray(data)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "set"]))
        i = draw(st.integers(0, max(0, len(b) - 1)))
        if op == "truncate":
            b = b[:i]
        elif op == "flip" and b:
            b[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            b[i:i] = draw(st.binary(min_size=1, max_size=16))
        elif op == "delete":
            del b[i : i + draw(st.integers(1, 16))]
        elif b:
            b[i] = draw(st.sampled_from([0x00, 0xFF, 0xD8, 0xD9, 0xDA, 0xC0, 0xC2, 0x7F, 0x80]))
    return bytes(b)


# --- JPEG and PNG ---------------------------------------------------------------------------------------
def _jpegs() -> list[bytes]:
    import cv2

    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    out = [encode_jpeg(img), encode_jpeg(np.zeros((8, 8, 3), np.uint8), quality=10)]
    for flags in ([cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_OPTIMIZE, 1]):
        out.append(cv2.imencode(".jpg", img, flags)[1].tobytes())
    out.append(cv2.imencode(".jpg", img[:, :, 0])[1].tobytes())  # grey
    return out


JPEGS = _jpegs()
PNG = encode_u16_png(np.arange(48, dtype=np.uint16).reshape(6, 8))


@st.composite
def lying_size(draw: st.DrawFn, data: bytes, marker: bytes, at: int, fmt: str) -> bytes:
    b = bytearray(data)
    i = b.find(marker)
    if i >= 0:
        b[i + at : i + at + struct.calcsize(fmt)] = struct.pack(fmt, *(draw(st.integers(0, 2 ** (8 * struct.calcsize(
            fmt) // 2) - 1)) for _ in range(2)))
    return bytes(b)


def jpeg_inputs() -> st.SearchStrategy[bytes]:
    base = st.sampled_from(JPEGS)
    return st.one_of(
        st.binary(max_size=512),
        base,
        base.flatmap(mutate),
        base.flatmap(lambda j: lying_size(j, b"\xff\xc0", 5, ">HH")),
        base.flatmap(lambda j: lying_size(j, b"\xff\xc2", 5, ">HH")),
        base.flatmap(lambda j: lying_size(j, b"\xff\xc0", 5, ">HH").flatmap(mutate)),
        st.just(PNG),
        st.builds(lambda b: b"\xff\xd8" + b, st.binary(max_size=256)),
    )


def check_jpeg(args: tuple[bytes, tuple[int, int] | None, float]) -> None:
    data, expected, floor = args
    for call in (lambda: jpeg_size(data), lambda: decode_jpeg(data, expected, 1_000_000, floor)):
        try:
            call()
        except JpegError:
            pass
    p = jpeg_problem(data, expected, 1_000_000, floor)
    assert p is None or (isinstance(p[0], str) and isinstance(p[1], str))


def check_png(data: bytes) -> None:
    for fn in (decode_u16_png, png_to_depth):
        try:
            fn(data)
        except JpegError:
            pass


# --- codec ------------------------------------------------------------------------------------------------
def check_envelope(args: tuple[bytes, type | None]) -> None:
    data, expected = args
    try:
        msg = decode(data, expected)
    except DecodeError:
        return
    assert expected is None or isinstance(msg, expected)
    # What decodes re-encodes and decodes to the same message (no half-validated state).
    assert decode(encode(msg), type(msg)) == msg


# --- the mapper's frame handler ---------------------------------------------------------------------------
@dataclass
class Sample:
    key_expr: str
    payload: zenoh.ZBytes
    attachment: zenoh.ZBytes | None


_NODE: list[MapperNode] = []


def mapper_node() -> MapperNode:
    if not _NODE:
        cfg = MapperConfig(site="fuzz", geometry=GeometryConfig(backend="oracle"),
                           perception=PerceptionConfig(segmenter="sim", embedder="sim"))
        _NODE.append(MapperNode(cfg, core=MapperCore(cfg)))
    return _NODE[0]


SIZES = [(INTR.width, INTR.height), (32, 24), (8, 8)]
SIZED_JPEGS = {wh: encode_jpeg(np.random.default_rng(1).integers(0, 255, (wh[1], wh[0], 3), dtype=np.uint8))
               for wh in SIZES}
POSE = view(EYES[0], 0).T_world_cam.tolist()  # type: ignore[union-attr]


@st.composite
def frames(draw: st.DrawFn) -> tuple[str, bytes, bytes | None]:
    """A frame sample: mostly a consistent key, header and JPEG, with one or more parts made hostile."""
    src = draw(st.sampled_from(["r1", "r2", "c1"]))
    w, h = draw(st.one_of(st.sampled_from(SIZES), st.sampled_from([(6000, 6000), (4096, 4097), (1, 16384)])))
    intr = draw(st.one_of(
        st.just(Intrinsics.from_fov(w, h, 70.0)), st.none(), STRATEGIES[FrameHeader].map(lambda x: x.intrinsics),
        st.builds(lambda f, c: Intrinsics.model_construct(width=w, height=h, fx=f, fy=f, cx=c, cy=c), floats, floats),
    ))
    pose = draw(st.one_of(st.just(POSE), st.none(), STRATEGIES[FrameHeader].map(lambda x: x.T_world_cam)))
    kind = "fixed" if src == "c1" else "robot"
    header = FrameHeader.model_construct(source_id=src, source_kind=kind, seq=draw(st.integers(0, 3)), stamp_ns=1,
                                         width=w, height=h, intrinsics=intr, T_world_cam=pose, pose_covariance=None,
                                         pose_trusted=draw(st.booleans()))
    try:
        att: bytes | None = encode(header)
    except Exception:  # noqa: BLE001 - a constructed (unvalidated) header that msgpack cannot pack
        att = None
    att = draw(st.one_of(st.just(att), st.just(att), st.none(), envelopes(kind="frame_header"),
                         st.just(att or b"").flatmap(mutate)))
    key = draw(st.one_of(st.just(KEYS.frame(kind, src)), st.just(KEYS.frame(kind, src)), frame_keys))
    jpeg = SIZED_JPEGS.get((w, h), JPEGS[0])
    jpeg = draw(st.one_of(st.just(jpeg), st.just(jpeg), jpeg_inputs(), st.just(jpeg).flatmap(mutate)))
    return key, jpeg, att


frame_keys = st.one_of(st.just(KEYS.robot_frame("r1")), st.just(KEYS.cam_frame("r1")), st.text(max_size=40),
                       st.just("argus/fuzz/robot//frame"), st.just("argus/fuzz/robot/a b/frame"))


def check_frame(args: tuple[str, bytes, bytes | None]) -> None:
    key, jpeg, att = args
    node = mapper_node()
    sample = Sample(key, zenoh.ZBytes(jpeg), None if att is None else zenoh.ZBytes(att))
    node.intake.admit(sample)  # type: ignore[arg-type]  # the callback's body: must never raise
    for _, f in node.intake.slots.take_all():
        rgb = node.intake.decode(f)
        if rgb is not None:
            node.intake.release(f)
            assert rgb.shape[2] == 3 and rgb.shape[0] * rgb.shape[1] == node.intake.working_pixels(f)
            assert rgb.shape[0] * rgb.shape[1] <= node.config.limits.max_working_pixels
    assert node.intake.decode_budget.in_flight == 0


# --- queries ---------------------------------------------------------------------------------------------
_CORE: list[MapperCore] = []


def query_core() -> MapperCore:
    if not _CORE:
        core = oracle_core()
        for i, eye in enumerate(EYES[:2]):
            core.ingest(view(eye, i))
        assert core.store.nodes
        _CORE.append(core)
    return _CORE[0]


numbers = st.one_of(floats.map(repr), ints.map(str), st.sampled_from(["nan", "inf", "-inf", "1e999", "", " 1", "0x1",
                                                                       "1_0", "١"]))
param_values = st.one_of(numbers, st.lists(numbers, max_size=4).map(",".join), st.text(max_size=12))
params = st.lists(
    st.tuples(st.sampled_from(["near", "radius", "label", "id", "since_version", "x", "", "near "]), param_values,
              st.sampled_from(["=", "", "=="])).map(lambda t: t[0] + t[2] + t[1]),
    max_size=5,
).map(";".join)
queries = st.one_of(params, st.text(max_size=60))


def check_query(text: str) -> None:
    try:
        q = GraphQuery.from_parameters(text)
    except ValueError:
        return
    query_core().query(q)
    GraphQuery.from_parameters(q.to_parameters())  # what a consumer builds from it parses again


# --- TOML configs and launch files -------------------------------------------------------------------------
CONFIG_MODELS: list[type] = [MapperConfig, PlannerNodeConfig, RobotAgentConfig, EdgeCameraConfig]
toml_keys = st.sampled_from([
    "id", "site", "zenoh.mode", "zenoh.connect", "limits.max_frame_pixels", "limits.site_min_m", "publish",
    "geometry.backend", "geometry.options", "ring_depth", "max_sources", "source.type", "body.type", "planner.strategy",
    "frames", "state_dir", "log_level", "a.b.c", "", "zenoh", "x-y", '"quoted key"', "perception.segmenter",
])
toml_values = st.one_of(
    ints.map(str), floats.map(lambda f: repr(f).replace("inf", "inf").replace("nan", "nan")),
    st.sampled_from(["true", "nan", "inf", "-inf", "1e999", "10000000000000000000000", '"x"', "[1, 2]", "{a = 1}",
                     '"tcp/127.0.0.1:7447"', '["tcp/127.0.0.1:1"]', "[[1]]", "{}", "1979-05-27", '"\\u0000"', "'''x'''",
                     '"mvs"', '"oracle"', '"sim"', '"../../etc"', "[", "0o7", "+1", "-0.0"]),
    st.text(max_size=20).map(lambda s: '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'),
)
toml_lines = st.one_of(
    st.tuples(toml_keys, toml_values).map(lambda kv: f"{kv[0]} = {kv[1]}"),
    st.sampled_from(["[zenoh]", "[limits]", "[[process]]", "[world]", "[process.settings]", "[source]", "[body]", "["]),
    st.text(max_size=30),
)
toml_texts = st.one_of(
    st.lists(toml_lines, max_size=8).map("\n".join).map(str.encode),
    st.binary(max_size=200),
    st.lists(toml_lines, max_size=8).map("\n".join).map(str.encode).flatmap(mutate),
)
overrides = st.lists(st.tuples(toml_keys, toml_values, st.sampled_from(["=", ""])).map(lambda t: t[0] + t[2] + t[1]),
                     max_size=3)


@dataclass
class TomlFile:
    path: Path


def check_toml(args: tuple[bytes, list[str], int], where: TomlFile) -> None:
    text, sets, which = args
    where.path.write_bytes(text)
    model = CONFIG_MODELS[which % len(CONFIG_MODELS)]
    for path, ov in ((where.path, []), (None, sets), (where.path, sets)):
        try:
            load_config(model, path, None, ov)
        except ConfigError:
            pass


launch_lines = st.one_of(
    toml_lines,
    st.sampled_from([
        'site = "demo"', 'endpoint = "tcp/127.0.0.1:7447"', "[[process]]", 'name = "mapper"', 'command = "mapper"',
        'args = ["--listen", "{endpoint}"]', "[process.settings]", 'config = "x.toml"', "restart = \"always\"",
        "max_restarts = -1", 'env = { A = "1" }', "[world]", 'family = "apartment"', "seed = -1", "seed = 1e3",
        'name = "a/b"', 'name = ""', "health_timeout_s = 0", 'role = ""', "required = 1",
    ]),
)
launch_texts = st.one_of(st.lists(launch_lines, max_size=12).map("\n".join).map(str.encode), st.binary(max_size=200))


def check_launch(text: bytes, where: TomlFile) -> None:
    where.path.write_bytes(text)
    try:
        load_launch(where.path)
    except ValueError:
        pass


# --- the campaign ------------------------------------------------------------------------------------------
@dataclass
class Target:
    strategy: st.SearchStrategy[Any]
    check: Callable[..., None]
    needs_file: bool = False


TARGETS: dict[str, Target] = {
    "jpeg": Target(st.tuples(jpeg_inputs(),
                             st.one_of(st.none(), st.tuples(st.integers(0, 70000), st.integers(0, 70000)),
                                       st.just((32, 24))),
                             st.sampled_from([0.0, 1000.0])), check_jpeg),
    "png": Target(st.one_of(st.binary(max_size=256), st.just(PNG).flatmap(mutate),
                            lying_size(PNG, b"IHDR", 4, ">II")), check_png),
    "envelope": Target(st.tuples(envelopes(), st.one_of(st.none(), st.sampled_from(WIRE_MESSAGES))), check_envelope),
    "frame": Target(frames(), check_frame),
    "query": Target(queries, check_query),
    "toml": Target(st.tuples(toml_texts, overrides, st.integers(0, 3)), check_toml, needs_file=True),
    "launch": Target(launch_texts, check_launch, needs_file=True),
}


def campaign(name: str, examples: int, tmp_path: Path) -> int:
    """Run one target for up to ``examples`` inputs (derandomized: the same inputs each run); returns how many ran."""
    target = TARGETS[name]
    where = TomlFile(tmp_path / f"{name}.toml")
    count = [0]

    @settings(max_examples=examples, derandomize=True, database=None, deadline=None,
              phases=[Phase.explicit, Phase.generate, Phase.shrink], suppress_health_check=list(HealthCheck))
    @given(target.strategy)
    def run(data: Any) -> None:
        count[0] += 1
        if target.needs_file:
            target.check(data, where)
        else:
            target.check(data)

    run()
    return count[0]


def test_every_peer_reachable_message_kind_is_fuzzed() -> None:
    assert set(STRATEGIES) == set(WIRE_MESSAGES) == set(REGISTRY.values())


@pytest.mark.parametrize("name", list(TARGETS))
def test_fuzz_short(name: str, tmp_path: Path) -> None:
    assert campaign(name, FAST_EXAMPLES, tmp_path) >= FAST_EXAMPLES // 2


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_fuzz_long(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    counts: dict[str, tuple[int, float]] = {}
    t0 = time.perf_counter()
    for name in TARGETS:
        t = time.perf_counter()
        counts[name] = (campaign(name, LONG_EXAMPLES, tmp_path), time.perf_counter() - t)
    wall = time.perf_counter() - t0
    total = sum(n for n, _ in counts.values())
    with capsys.disabled():
        print("\nfuzz campaign (derandomized hypothesis): inputs per target, seconds")
        for name, (n, s) in counts.items():
            print(f"  {name:10s} {n:8d}  {s:7.1f} s")
        print(f"  {'total':10s} {total:8d}  {wall:7.1f} s, 0 unhandled exceptions")
    assert total >= 100_000


# --- what the campaign found (regressions) ------------------------------------------------------------------
def test_a_config_file_that_is_not_utf8_is_a_config_error(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_bytes(b"\x80")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_config(MapperConfig, p)
