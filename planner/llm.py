"""Completion sampler backed by any OpenAI-compatible chat-completions endpoint (e.g. a local server).

The prompt carries the graph compactly (rooms with extents, objects with ids, labels, rounded
positions, support parents). The reply must be strict JSON matching :class:`LlmReply`; anything
else (timeouts, HTTP errors, prose, schema violations) is retried, then the embedded prior sampler
takes over with a logged warning. Only the standard library talks HTTP (urllib).
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
import urllib.error
import urllib.request
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from planner.completion import Completion, CompletionSampler, HypObject, SamplerInfo, SceneContext
from planner.config import LlmConfig

log = logging.getLogger(__name__)
MAX_REPLY_BYTES = 1 << 20
MAX_OBJECTS_PER_COMPLETION = 200


class LlmObject(BaseModel):
    """One hypothesised object in the model's reply."""

    model_config = ConfigDict(extra="forbid")
    label: str = Field(min_length=1, max_length=64, description="object label, e.g. 'coffee table'")
    room: str | None = Field(default=None, max_length=64, description="room name from the prompt, if any")
    on: str | None = Field(default=None, max_length=64, description="id of the graph object it stands on")
    x: float | None = Field(default=None, ge=-1e4, le=1e4, description="rough x, metres")
    y: float | None = Field(default=None, ge=-1e4, le=1e4, description="rough y, metres")


class LlmCompletion(BaseModel):
    model_config = ConfigDict(extra="forbid")
    objects: list[LlmObject] = Field(max_length=MAX_OBJECTS_PER_COMPLETION, description="unobserved objects")


class LlmReply(BaseModel):
    """The strict JSON the model must answer with."""

    model_config = ConfigDict(extra="forbid")
    completions: list[LlmCompletion] = Field(min_length=1, max_length=64, description="scene completions")


class LlmReplyError(ValueError):
    """The endpoint answered, but not with a valid reply."""


SYSTEM_PROMPT = (
    "You complete partially observed indoor scenes for a robot that explores them. Given the rooms and "
    "the objects already detected, propose plausible objects that are present but NOT yet detected. "
    "Answer with JSON only, no prose, exactly in this form: "
    '{"completions": [{"objects": [{"label": str, "room": str|null, "on": str|null, "x": float|null, '
    '"y": float|null}]}]}. Use room names from the input; "on" is the id of a detected object the new '
    "object stands on (for small items), else null; x, y are rough metre positions inside the room or null. "
    "Make the completions differ where the scene is uncertain."
)


def build_prompt(ctx: SceneContext, k: int, max_nodes: int) -> str:
    """The user message: the graph in compact JSON."""
    rooms = [
        {
            "name": r.name,
            "kind": r.kind,
            "x": [round(float(r.xy_min[0]), 1), round(float(r.xy_max[0]), 1)],
            "y": [round(float(r.xy_min[1]), 1), round(float(r.xy_max[1]), 1)],
        }
        for r in ctx.rooms
    ]
    objs = []
    for o in ctx.objects[:max_nodes]:
        c = o.node.centroid
        item: dict[str, Any] = {
            "id": o.node.node_id,
            "label": o.node.label,
            "xyz": [round(float(v), 1) for v in c],
        }
        if o.room:
            item["room"] = o.room
        if o.parent_id:
            item["on"] = o.parent_id
        objs.append(item)
    body = {"rooms": rooms, "detected_objects": objs, "n_completions": k}
    return (
        f"Scene so far (metres, z up):\n{json.dumps(body, separators=(',', ':'))}\n"
        f"Return {k} completions of the objects not yet detected."
    )


def parse_reply(content: str) -> LlmReply:
    """Strict parse of the model's message content (a ```json fence around it is tolerated)."""
    text = content.strip()
    m = re.fullmatch(r"```(?:json)?\s*(.*?)\s*```", text, flags=re.S)
    if m:
        text = m.group(1)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise LlmReplyError(f"reply is not JSON: {e.msg} at {e.pos}") from None
    try:
        return LlmReply.model_validate(data)
    except ValidationError as e:
        raise LlmReplyError(
            f"reply does not match the schema: {e.error_count()} error(s): {e.errors()[0]['msg']}"
        ) from None


def to_completions(reply: LlmReply, ctx: SceneContext) -> list[Completion]:
    """Reply objects as completions; unknown rooms and parents are dropped, not trusted."""
    rooms = {r.name for r in ctx.rooms}
    ids = {o.node.node_id for o in ctx.objects}
    out = []
    for comp in reply.completions:
        objs = []
        for o in comp.objects:
            room = o.room if o.room in rooms else None
            parent = o.on if o.on in ids else None
            xyz = None
            if o.x is not None and o.y is not None and parent is None:
                xyz = (float(o.x), float(o.y), 0.0)
            if room is None and parent is None and xyz is None and ctx.rooms:
                continue
            objs.append(HypObject(o.label, room, parent, xyz))
        out.append(Completion(tuple(objs), source="llm"))
    return out


class LlmSampler:
    """Completions from a chat-completions endpoint, with retries and a prior fallback."""

    name = "llm"

    def __init__(self, config: LlmConfig, fallback: CompletionSampler) -> None:
        self.config = config
        self.fallback = fallback
        self.info = SamplerInfo()
        self.failures = 0

    def _request(self, messages: list[dict[str, str]]) -> str:
        cfg = self.config
        payload: dict[str, Any] = {
            "model": cfg.model,
            "messages": messages,
            "temperature": cfg.temperature,
            "max_tokens": cfg.max_tokens,
        }
        if cfg.json_mode:
            payload["response_format"] = {"type": "json_object"}
        headers = {"Content-Type": "application/json"}
        key = os.environ.get(cfg.api_key_env)
        if key:
            headers["Authorization"] = f"Bearer {key}"
        url = cfg.base_url.rstrip("/") + "/chat/completions"
        req = urllib.request.Request(url, data=json.dumps(payload).encode(), headers=headers, method="POST")
        with urllib.request.urlopen(req, timeout=cfg.timeout_s) as resp:  # noqa: S310 - configured endpoint
            raw = resp.read(MAX_REPLY_BYTES + 1)
        if len(raw) > MAX_REPLY_BYTES:
            raise LlmReplyError("reply too large")
        try:
            body = json.loads(raw)
            content = body["choices"][0]["message"]["content"]
        except (ValueError, KeyError, IndexError, TypeError) as e:
            raise LlmReplyError(f"not a chat-completions response: {type(e).__name__}") from None
        if not isinstance(content, str):
            raise LlmReplyError("message content is not a string")
        return content

    def sample(self, ctx: SceneContext, k: int, rng: np.random.Generator) -> list[Completion]:
        t0 = time.perf_counter()
        self.info = SamplerInfo(requested=k)
        messages = [
            {"role": "system", "content": SYSTEM_PROMPT},
            {"role": "user", "content": build_prompt(ctx, k, self.config.max_nodes_in_prompt)},
        ]
        error = None
        for attempt in range(self.config.retries + 1):
            try:
                comps = to_completions(parse_reply(self._request(messages)), ctx)[:k]
                if len(comps) < k:
                    comps += self.fallback.sample(ctx, k - len(comps), rng)
                self.info.produced = len(comps)
                self.info.latency_s = time.perf_counter() - t0
                return comps
            except (urllib.error.URLError, TimeoutError, OSError, LlmReplyError) as e:
                error = f"{type(e).__name__}: {e}"
                log.debug("llm attempt %d failed: %s", attempt + 1, error)
        self.failures += 1
        log.warning("llm sampler failed (%s); falling back to the prior sampler", error)
        comps = self.fallback.sample(ctx, k, rng)
        self.info = SamplerInfo(
            requested=k, produced=len(comps), fallback=True, error=error, latency_s=time.perf_counter() - t0
        )
        return comps


def make_llm_sampler(config: Any, prior: Any) -> CompletionSampler:
    """Factory of the ``llm`` sampler (``config``: the PlannerConfig), falling back to the prior."""
    from planner.completion import PriorSampler

    return LlmSampler(config.sampler.llm, fallback=PriorSampler(prior))
