"""The embedded world: procedural apartments and furnished rooms, a CPU renderer, navigation, ground truth.

Modules: ``scene`` (generate_scene, Scene, SceneObject, Room), ``render`` (Renderer, RenderOutput),
``nav`` (NavMap), ``robot`` (SimRobot, OdometryNoise), ``cameras`` (place_fixed_cameras, FixedCamera),
``io`` (glTF + JSON export/load), ``cli`` (``argus sim ...``). Nothing is imported here, so importing
``sim`` stays cheap.
"""
