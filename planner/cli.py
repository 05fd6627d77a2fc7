"""``argus planner``: send each robot its next-best view from the live scene graph.

Example::

    argus planner --connect tcp/127.0.0.1:7447 --strategy asp
    argus planner --strategy asp --sampler llm --llm-url http://127.0.0.1:8000/v1 --llm-model qwen2.5-7b
"""

from __future__ import annotations

import argparse
import sys

from protocol.tomlconfig import ConfigError, describe, load_config, process_parser, process_values

EPILOG = """examples:
  argus planner --connect tcp/127.0.0.1:7447                  # asp with the embedded prior
  argus planner --strategy see                                # geometric frontier baseline
  argus planner --sampler llm --llm-url http://127.0.0.1:8000/v1 --llm-model my-model
  argus planner --set planner.asp.n_completions=16 --set planner.asp.travel_weight_per_m=0.02
  argus planner --describe                                    # every config field

The llm sampler reads its API key from the env var named by planner.sampler.llm.api_key_env
(ARGUS_LLM_API_KEY by default; may be unset for a local server) and falls back to the prior
when the endpoint fails. Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error."""


def parser() -> argparse.ArgumentParser:
    p = process_parser(
        "argus planner",
        "Score the robots' candidate viewpoints against the scene graph and publish NBV goals.",
        EPILOG, what="planner", config_help="TOML config file", set_example="planner.asp.n_jitter=2",
    )
    p.add_argument(
        "--strategy", choices=["see", "asp"], default=None, help="see (geometric) or asp (semantic)"
    )
    p.add_argument("--sampler", choices=["prior", "llm"], default=None, help="asp completion sampler")
    p.add_argument(
        "--llm-url", default=None, help="OpenAI-compatible base URL, e.g. http://127.0.0.1:8000/v1"
    )
    p.add_argument("--llm-model", default=None, help="model name for the llm sampler")
    p.add_argument("--llm-key-env", default=None, help="env var holding the llm API key")
    p.add_argument("--completions", type=int, default=None, help="completions K per decision")
    p.add_argument("--seed", type=int, default=None, help="sampler seed")
    return p


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    from planner.config import PlannerNodeConfig

    if a.describe:
        print("\n".join(["argus planner configuration (TOML):", "", *describe(PlannerNodeConfig)]))
        return 0
    values = {
        **process_values(a, id_field="node_id"),
        "planner.strategy": a.strategy,
        "planner.sampler.kind": a.sampler,
        "planner.sampler.llm.base_url": a.llm_url,
        "planner.sampler.llm.model": a.llm_model,
        "planner.sampler.llm.api_key_env": a.llm_key_env,
        "planner.asp.n_completions": a.completions,
        "planner.seed": a.seed,
    }
    try:
        config = load_config(PlannerNodeConfig, a.config, values, a.overrides)
    except ConfigError as e:
        print(f"argus planner: {e}", file=sys.stderr)
        return 2
    from protocol.runtime import setup_logging

    setup_logging(f"planner[{config.node_id}]", config.log_level)
    from planner.node import run

    try:
        return run(config)
    except (OSError, ValueError) as e:
        print(f"argus planner: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
