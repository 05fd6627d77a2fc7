"""``argus planner``: send each robot its next-best view from the live scene graph.

Example::

    argus planner --connect tcp/127.0.0.1:7447 --strategy asp
    argus planner --strategy asp --sampler llm --llm-url http://127.0.0.1:8000/v1 --llm-model qwen2.5-7b
"""

from __future__ import annotations

import argparse
import sys

from protocol.tomlconfig import Flag, ProcessCommand

EPILOG = """examples:
  argus planner --connect tcp/127.0.0.1:7447                  # asp with the embedded prior
  argus planner --strategy see                                # geometric frontier baseline
  argus planner --sampler llm --llm-url http://127.0.0.1:8000/v1 --llm-model my-model
  argus planner --set planner.asp.n_completions=16 --set planner.asp.travel_weight_per_m=0.02
  argus planner --describe                                    # every config field

The llm sampler reads its API key from the env var named by planner.sampler.llm.api_key_env
(ARGUS_LLM_API_KEY by default; may be unset for a local server) and falls back to the prior
when the endpoint fails. Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error."""


COMMAND = ProcessCommand(
    "planner", "Score the robots' candidate viewpoints against the scene graph and publish NBV goals.",
    EPILOG, what="planner", config_help="TOML config file", set_example="planner.asp.n_jitter=2",
    node_module="planner.node", id_field="node_id",
    flags=(
        Flag("--strategy", "planner.strategy", "see (geometric) or asp (semantic)", choices=("see", "asp")),
        Flag("--sampler", "planner.sampler.kind", "asp completion sampler", choices=("prior", "llm")),
        Flag("--llm-url", "planner.sampler.llm.base_url", "OpenAI-compatible base URL, e.g. http://127.0.0.1:8000/v1"),
        Flag("--llm-model", "planner.sampler.llm.model", "model name for the llm sampler"),
        Flag("--llm-key-env", "planner.sampler.llm.api_key_env", "env var holding the llm API key"),
        Flag("--completions", "planner.asp.n_completions", "completions K per decision", int),
        Flag("--seed", "planner.seed", "sampler seed", int),
    ),
)


def parser() -> argparse.ArgumentParser:
    return COMMAND.parser()


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    from planner.config import PlannerNodeConfig

    return COMMAND.start(a, PlannerNodeConfig, errors=(OSError, ValueError))


if __name__ == "__main__":
    sys.exit(main())
