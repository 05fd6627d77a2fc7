"""Mapper geometry: RGB-only metric reconstruction behind a MapAnything-style ``Reconstructor``.

``contract`` holds the shared types and ``compose``; ``registry.make_reconstructor`` builds a backend
(``mvs`` default, ``oracle``, ``mapanything``). Importing this package loads nothing heavy.

Typical use per keyframe (what the mapper does)::

    rec = make_reconstructor("mvs")
    window = last_keyframes + [new_view]                      # ~5 views, priors in View.T_world_cam
    recon = rec.reconstruct(window, targets=[len(window) - 1])  # dense depth for the new view only
    geom = compose(recon, anchor_pose(recon, window))           # metric points, z-depth, refined poses
    use = geom.confidence[-1] >= CONFIDENT                      # fuse only confident pixels

A camera without extrinsics: ``est = rec.register(view, keyframes_from_geometry(views, geom))`` and use
``est.T_world_cam`` only when ``est.ok`` (``est.reason`` says why not).
"""
