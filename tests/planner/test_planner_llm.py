"""The llm completion sampler against a small local OpenAI-compatible server (canned and bad replies)."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from planner import synthetic as S
from planner.completion import PriorSampler, build_context, rooms_from_viewpoints
from planner.config import LlmConfig, PlannerConfig, SamplerConfig
from planner.core import Planner
from planner.llm import LlmReplyError, LlmSampler, parse_reply
from planner.prior import load_prior

GOOD = {
    "completions": [
        {
            "objects": [
                {"label": "nightstand", "room": "bedroom_1", "on": None, "x": 1.0, "y": 6.0},
                {"label": "cup", "room": "living_room", "on": "n1", "x": None, "y": None},
            ]
        },
        {
            "objects": [
                {"label": "wardrobe", "room": "bedroom_1", "on": None, "x": None, "y": None},
                {"label": "ghost", "room": "attic", "on": "n999", "x": None, "y": None},
            ]
        },
    ]
}


class FakeLlm:
    """Serves /v1/chat/completions with a reply chosen by ``mode``; records the requests."""

    def __init__(self) -> None:
        self.mode = "good"
        self.requests: list[dict] = []
        self.release = threading.Event()
        fake = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:
                pass

            def do_POST(self) -> None:  # noqa: N802 - http.server API
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                fake.requests.append(
                    {"path": self.path, "body": body, "auth": self.headers.get("Authorization")}
                )
                if fake.mode == "slow":
                    fake.release.wait(10.0)  # hold the reply until the test is done with it
                content = {
                    "good": json.dumps(GOOD),
                    "fenced": "```json\n" + json.dumps(GOOD) + "\n```",
                    "prose": "Sure! Here are some objects: a bed and a lamp.",
                    "schema": json.dumps({"completions": [{"objects": [{"label": 3, "colour": "red"}]}]}),
                    "slow": json.dumps(GOOD),
                }.get(fake.mode)
                if fake.mode == "http500":
                    self.send_response(500)
                    self.end_headers()
                    return
                data = (
                    b"{not json"
                    if fake.mode == "badbody"
                    else json.dumps(
                        {"choices": [{"message": {"role": "assistant", "content": content}}]}
                    ).encode()
                )
                self.send_response(200)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/v1"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.release.set()
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def fake_llm() -> Iterator[FakeLlm]:
    f = FakeLlm()
    try:
        yield f
    finally:
        f.close()


def context():
    prior = load_prior()
    w = S.apartment(0)
    name = S.room_namer(w["rooms"])
    vset = S.grid_viewpoints("r1", (0.6, 0.6), (9.4, 8.4), spacing_m=1.0, room_of=name)
    vps = [v for v in vset.viewpoints if v.room]
    rooms = rooms_from_viewpoints([v.room for v in vps], np.array([[v.x, v.y] for v in vps]), prior)
    nodes = [S.node("n1", "coffee table", (2.0, 2.2, 0.22), (1.1, 0.6, 0.45))]
    return prior, build_context(nodes, [], rooms, prior)


def sampler(url: str, **kw: object) -> LlmSampler:
    prior, _ = context()
    opts: dict = {"timeout_s": 2.0, "retries": 1, **kw}
    cfg = LlmConfig(base_url=url, model="test-model", **opts)
    return LlmSampler(cfg, fallback=PriorSampler(prior))


def test_parses_a_good_reply(fake_llm: FakeLlm, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ARGUS_LLM_API_KEY", "sekret")
    _, ctx = context()
    s = sampler(fake_llm.url)
    comps = s.sample(ctx, 2, np.random.default_rng(0))
    assert not s.info.fallback and len(comps) == 2
    a, b = comps
    assert [(o.label, o.room, o.parent) for o in a.objects] == [
        ("nightstand", "bedroom_1", None),
        ("cup", "living_room", "n1"),
    ]
    assert a.objects[0].xyz is not None and a.objects[0].xyz[:2] == (1.0, 6.0)
    # Unknown room and parent are not trusted: the object has nowhere to go and is dropped.
    assert [o.label for o in b.objects] == ["wardrobe"]
    req = fake_llm.requests[0]
    assert req["path"] == "/v1/chat/completions" and req["body"]["model"] == "test-model"
    assert req["auth"] == "Bearer sekret"
    user = req["body"]["messages"][1]["content"]
    assert "coffee table" in user and "bedroom_1" in user


def test_short_reply_is_topped_up_from_the_prior(fake_llm: FakeLlm) -> None:
    _, ctx = context()
    s = sampler(fake_llm.url)
    comps = s.sample(ctx, 5, np.random.default_rng(0))
    assert len(comps) == 5 and [c.source for c in comps[:2]] == ["llm", "llm"]
    assert all(c.source == "prior" for c in comps[2:])


@pytest.mark.parametrize("mode", ["prose", "schema", "badbody", "http500"])
def test_bad_replies_fall_back_to_the_prior(
    fake_llm: FakeLlm, mode: str, caplog: pytest.LogCaptureFixture
) -> None:
    fake_llm.mode = mode
    _, ctx = context()
    s = sampler(fake_llm.url)
    with caplog.at_level("WARNING", logger="planner.llm"):
        comps = s.sample(ctx, 4, np.random.default_rng(0))
    assert s.info.fallback and s.info.error
    assert len(comps) == 4 and all(c.source == "prior" for c in comps)
    assert len(fake_llm.requests) == 2  # one retry
    assert any("falling back" in r.message for r in caplog.records)


def test_respects_its_timeout(fake_llm: FakeLlm) -> None:
    fake_llm.mode = "slow"
    _, ctx = context()
    s = sampler(fake_llm.url, timeout_s=0.4, retries=0)
    t0 = time.monotonic()
    comps = s.sample(ctx, 3, np.random.default_rng(0))
    elapsed = time.monotonic() - t0
    assert s.info.fallback and "timed out" in (s.info.error or "").lower()
    assert elapsed < 3.0 and len(comps) == 3


def test_unreachable_endpoint_falls_back() -> None:
    _, ctx = context()
    s = sampler("http://127.0.0.1:9/v1", timeout_s=0.5, retries=0)  # discard port: nothing listens
    comps = s.sample(ctx, 2, np.random.default_rng(0))
    assert s.info.fallback and len(comps) == 2


class TestParse:
    def test_fenced_json_accepted(self) -> None:
        assert len(parse_reply("```json\n" + json.dumps(GOOD) + "\n```").completions) == 2

    @pytest.mark.parametrize(
        "text",
        [
            "",
            "null",
            "[]",
            '{"completions": []}',
            '{"completions": [{}]}',
            '{"completions": [{"objects": []}], "extra": 1}',
            "{'single': 'quotes'}",
        ],
    )
    def test_rejects(self, text: str) -> None:
        with pytest.raises(LlmReplyError):
            parse_reply(text)


def test_planner_with_llm_sampler_plans(fake_llm: FakeLlm) -> None:
    w = S.apartment(0)
    name = S.room_namer(w["rooms"])
    vset = S.grid_viewpoints("r1", (0.6, 0.6), (9.4, 8.4), spacing_m=1.0, room_of=name)
    vset = vset.model_copy(update={"viewpoints": [v for v in vset.viewpoints if v.room]})
    pts = w["points"]
    pm = S.point_map(pts[(pts[:, 0] < 6) & (pts[:, 1] < 5)], 0.05)
    cfg = PlannerConfig(
        strategy="asp", sampler=SamplerConfig(kind="llm", llm=LlmConfig(base_url=fake_llm.url))
    )
    planner = Planner(cfg)
    goals = planner.plan(
        S.snapshot([S.node("n1", "coffee table", (2.0, 2.2, 0.22), (1.1, 0.6, 0.45))]),
        pm,
        {"r1": (S.robot_state("r1", 3.0, 2.5, 0.0), vset)},
    )
    assert len(goals) == 1 and planner.info.sampler == "llm" and not planner.info.sampler_fallback
    assert planner.info.n_hypotheses > 0
