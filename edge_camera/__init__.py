"""``argus edge-camera``: one fixed camera's JPEG frames on Zenoh.

A light process for a Raspberry Pi class box: grab from a source backend (OpenCV device, RTSP/HTTP
stream, video file, image folder, recorded sequence with poses, test pattern, or a fixed camera in
the embedded simulated world), resize, JPEG-encode, publish at a bounded rate with calibration in the
header, announce itself with a liveliness token and reconnect on every transient fault. Importing
this package has no side effects and pulls in neither torch nor the simulator.
"""
