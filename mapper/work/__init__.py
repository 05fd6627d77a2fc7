"""Scaling the mapper out: keyframe jobs for ``argus worker`` processes over Zenoh.

- :mod:`mapper.work.compute`: the heavy per-keyframe work (geometry + 2D perception), the same code wherever
  it runs;
- :mod:`mapper.work.jobs`: jobs and results on the wire (compressed depth, validation of what a worker sends);
- :mod:`mapper.work.dispatch`: the dispatcher's state machine (pending / assigned / acked / done, re-issue,
  quarantine), pure;
- :mod:`mapper.work.offload`: the mapper's side (liveliness of workers, the keyframe store queryable);
- :mod:`mapper.work.latency`: where a keyframe's capture-to-graph time goes, stage by stage (``kf_s.*`` in the
  mapper's status), pure;
- :mod:`mapper.work.worker`: the ``argus worker`` process.
"""
