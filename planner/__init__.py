"""Next-best-view planning from the scene graph: ``argus planner``.

Pure core: :class:`planner.core.Planner` (strategies ``see`` and ``asp``), completion samplers
(``prior``: protocol/data/indoor_prior.json; ``llm``: any OpenAI-compatible chat endpoint). The Zenoh
process lives in :mod:`planner.node`; nothing here imports the simulator.
"""
