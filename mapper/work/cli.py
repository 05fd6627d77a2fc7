"""``argus worker``: take keyframe jobs (geometry + 2D perception) off the mapper of a site.

Example::

    argus worker --connect tcp/127.0.0.1:7447 --id gpu0
"""

from __future__ import annotations

import sys

from protocol.tomlconfig import ProcessCommand

EPILOG = """The mapper stays the single writer of the graph; a worker does the heavy per-keyframe work: it
reconstructs the keyframe with its source keyframes (their JPEGs fetched from the mapper's keyframe store),
runs 2D perception on it and returns depth, confidence, the refined pose and the detections. The settings
(geometry and perception backends, fusion thresholds) come with each job from the mapper, so a worker needs no
backend flags. The mapper sends jobs only while a worker's liveliness token is there and re-issues those of a
worker that went away; with no worker running it does every keyframe itself.

Run one per machine or per GPU, each with its own --id, connected to the site's router. On another machine,
connect to the router over TLS (deploy/launch/multi-machine.toml).

examples:
  argus worker --connect tcp/127.0.0.1:7447 --id w1
  argus worker --connect tls/192.168.1.10:7447 --zenoh-config client-tls.json5 --id gpu0 --set torch_threads=8
  argus worker --describe                      # every config field

Status: argus/<site>/status/worker/<id> (jobs_in, jobs_done, jobs_failed, jobs_busy, keyframes_fetched,
image_cache_hits, job_s_mean). Exit status: 0 after SIGINT/SIGTERM, 2 on a configuration error."""


COMMAND = ProcessCommand(
    "worker", "Do the mapper's heavy per-keyframe work (geometry, 2D perception).", EPILOG, what="worker",
    config_help="TOML config file", set_example="torch_threads=1", node_module="mapper.work.worker",
)


def main(argv: list[str] | None = None) -> int:
    a = COMMAND.parser().parse_args(argv)
    from mapper.work.config import WorkerConfig

    return COMMAND.start(a, WorkerConfig)


if __name__ == "__main__":
    sys.exit(main())
