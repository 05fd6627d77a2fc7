"""Mapper geometry: RGB-only metric reconstruction behind a MapAnything-style ``Reconstructor``.

``contract`` holds the shared types and ``compose``; ``registry.make_reconstructor`` builds a backend
(``mvs`` default, ``oracle``, ``mapanything``). Importing this package loads nothing heavy.
"""
