"""Integration tests of ``argus edge-camera``: real CLI processes on loopback with a real router."""

from __future__ import annotations

import json
import shutil
import signal
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol.codec import decode
from protocol.jpeg import decode_jpeg
from protocol.keys import Keys
from tests.support.procs import FramePeer, Proc, wait_for

KEYS = Keys("default")


class Listener(FramePeer):
    """A client session collecting frames, Status messages and liveliness changes of one camera."""

    def __init__(self, router: str, camera_id: str) -> None:
        super().__init__(router, KEYS.cam_frame(camera_id), KEYS.status("edge-camera", camera_id))
        self.alive_events: list[str] = []
        self._subs.append(self.session.liveliness().declare_subscriber(
            KEYS.alive("edge-camera", camera_id), self._on_alive, history=True))

    def _on_alive(self, sample) -> None:  # noqa: ANN001
        with self._lock:
            self.alive_events.append(str(sample.kind))


@pytest.fixture
def listener_factory():
    made: list[Listener] = []

    def make(router: str, camera_id: str) -> Listener:
        lst = Listener(router, camera_id)
        made.append(lst)
        return lst

    yield make
    for lst in made:
        lst.close()


def write_images(folder: Path, n: int, size: tuple[int, int] = (200, 150), start: int = 0) -> list[np.ndarray]:
    """``n`` PNGs of distinct flat colours (w x h = size); returns the RGB images."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(start, start + n):
        rgb = np.zeros((size[1], size[0], 3), np.uint8)
        rgb[:] = ((40 * i) % 256, 255 - (30 * i) % 256, 128)
        cv2.imwrite(str(folder / f"img_{i:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        out.append(rgb)
    return out


def write_config(path: Path, router: str, source: str, extra: str = "") -> Path:
    path.write_text(
        f"""id = "cam_t"
status_period_s = 0.2
{extra}
[source]
{source}
[publish]
max_rate_hz = 20.0
width = 160
jpeg_quality = 90
[reconnect]
initial_s = 0.1
max_s = 0.3
[zenoh]
mode = "client"
connect = ["{router}"]
"""
    )
    return path


def test_folder_source_publishes_frames_with_calibration(tmp_path, router, procs, listener_factory):
    images = write_images(tmp_path / "imgs", 3)
    calib = tmp_path / "calib.json"
    T = [[0.0, 0.0, 1.0, 1.0], [-1.0, 0.0, 0.0, 2.0], [0.0, -1.0, 0.0, 2.5], [0.0, 0.0, 0.0, 1.0]]
    calib.write_text(json.dumps({
        "intrinsics": {"width": 200, "height": 150, "fx": 100.0, "fy": 100.0, "cx": 99.5, "cy": 74.5},
        "T_world_cam": T,
    }))
    cfg = write_config(
        tmp_path / "cam.toml", router,
        f'type = "folder"\npath = "{tmp_path / "imgs"}"\nrate_hz = 20.0\n',
        extra=f'calibration = "{calib}"',
    )
    lst = listener_factory(router, "cam_t")
    proc = Proc(["edge-camera", "--config", str(cfg)])
    procs.append(proc)
    wait_for(lambda: lst.n_frames() >= 4, timeout=30, what=f"4 frames; output:\n{proc.output}")
    frames = list(lst.frames)
    seqs = [f.header.seq for f in frames]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    for f in frames:
        rgb = decode_jpeg(f.jpeg)
        assert rgb.shape == (120, 160, 3)
        h = f.header
        assert (h.source_id, h.source_kind, h.width, h.height) == ("cam_t", "fixed", 160, 120)
        assert h.intrinsics is not None and h.intrinsics.width == 160
        assert h.intrinsics.fx == pytest.approx(80.0)
        assert h.intrinsics.cx == pytest.approx((99.5 + 0.5) * 0.8 - 0.5)
        assert np.allclose(np.asarray(h.T_world_cam), T)
        assert h.pose_trusted is True
    # Images go out in sorted name order and keep their colour through resize + JPEG.
    first = decode_jpeg(frames[0].jpeg).reshape(-1, 3).mean(axis=0)
    idx = frames[0].header.seq % 3
    assert np.allclose(first, images[idx][0, 0], atol=6)
    wait_for(lambda: any(s.counters.get("frames_sent", 0) >= 1 for s in lst.statuses), timeout=10,
             what="a Status with frames_sent")
    assert any(ev.endswith("PUT") for ev in lst.alive_events)
    proc.signal()
    assert proc.wait(timeout=15) == 0
    wait_for(lambda: any(ev.endswith("DELETE") for ev in lst.alive_events), timeout=10,
             what="the liveliness token withdrawn")


def test_folder_emptied_mid_stream_reconnects_and_stays_up(tmp_path, router, procs, listener_factory):
    folder = tmp_path / "imgs"
    write_images(folder, 2)
    cfg = write_config(tmp_path / "cam.toml", router, f'type = "folder"\npath = "{folder}"\nrate_hz = 20.0\n')
    lst = listener_factory(router, "cam_t")
    proc = Proc(["edge-camera", "--config", str(cfg)])
    procs.append(proc)
    wait_for(lambda: lst.n_frames() >= 2, timeout=30, what=f"first frames; output:\n{proc.output}")
    shutil.rmtree(folder)

    def reports_fault() -> bool:
        return any(
            s.last_error and "imgs" in s.last_error and s.counters.get("reconnect_attempts", 0) >= 2
            for s in list(lst.statuses)
        )

    wait_for(reports_fault, timeout=20, what=f"Status with the error and reconnect attempts:\n{proc.output}")
    assert proc.alive()
    assert any(s.state == "degraded" for s in lst.statuses)
    n_before = lst.n_frames()
    write_images(folder, 2, start=5)
    wait_for(lambda: lst.n_frames() >= n_before + 2, timeout=20, what="frames after the folder came back")
    wait_for(lambda: any(s.counters.get("reconnects", 0) >= 1 and s.state == "ok" for s in list(lst.statuses)),
             timeout=10, what="Status ok after reconnecting")
    assert proc.alive()


def test_dead_device_never_says_publishing_and_opencv_stays_quiet(tmp_path, router, procs, listener_factory):
    """Issue 38: "publishing on ..." was logged before the source had opened, and a dead device's retries mixed
    OpenCV's own [ WARN ] lines into the log."""
    cfg = write_config(tmp_path / "cam.toml", router, 'type = "opencv"\ndevice = 63\n')
    lst = listener_factory(router, "cam_t")
    proc = Proc(["edge-camera", "--config", str(cfg)])
    procs.append(proc)
    wait_for(lambda: any(s.counters.get("reconnect_attempts", 0) >= 3 for s in list(lst.statuses)), timeout=30,
             what=f"three failed opens:\n{proc.output}")
    proc.signal()
    assert proc.wait(timeout=15) == 0
    out = proc.output
    assert "publishing on" not in out and "[ WARN" not in out and "VIDEOIO" not in out, out
    assert out.count("source open failed: cannot open camera device 63") == 1, out  # then one line a minute
    assert any(s.state == "degraded" for s in lst.statuses)


def test_publishing_is_logged_once_the_source_is_open(tmp_path, router, procs, listener_factory):
    folder = tmp_path / "late"
    cfg = write_config(tmp_path / "cam.toml", router, f'type = "folder"\npath = "{folder}"\nrate_hz = 20.0\n')
    lst = listener_factory(router, "cam_t")
    proc = Proc(["edge-camera", "--config", str(cfg)])
    procs.append(proc)
    wait_for(lambda: "source open failed" in proc.output, timeout=30, what=f"a failed open:\n{proc.output}")
    assert "publishing on" not in proc.output
    write_images(folder, 2)
    wait_for(lambda: lst.n_frames() >= 1, timeout=30, what=f"frames once the folder exists:\n{proc.output}")
    lines = proc.output.splitlines()
    (at,) = [i for i, line in enumerate(lines) if "source open; publishing on argus/default/cam/cam_t/frame" in line]
    assert any("source open failed" in line for line in lines[:at])


@pytest.mark.parametrize(
    ("source", "extra", "message"),
    [
        ('type = "no_such_source"', "", "unknown source type"),
        ('type = "pattern"', 'calibration = "/nonexistent/calib.yaml"', "calibration file"),
        ('type = "pattern"', 'calibration = "BADFILE"', "calibration"),
        ('type = "recorded"\npath = "/nonexistent/seq"', "", "/nonexistent/seq/frames does not exist"),
    ],
)
@pytest.mark.integration
def test_configuration_errors_exit_nonzero_with_a_message(tmp_path, source, extra, message):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    extra = extra.replace("BADFILE", str(bad))
    cfg = write_config(tmp_path / "cam.toml", "tcp/127.0.0.1:9", source, extra=extra)
    proc = Proc(["edge-camera", "--config", str(cfg)])
    try:
        rc = proc.wait(timeout=30)
    finally:
        proc.stop()
    assert rc == 2
    assert message in proc.output


def test_sim_source_publishes_frames_and_oracle(tmp_path, router, procs, listener_factory):
    pytest.importorskip("sim.scene")
    from protocol.messages import OracleFrame
    from protocol.oracle import png_to_depth

    cfg = write_config(
        tmp_path / "cam.toml", router,
        'type = "sim"\nfamily = "furnished_room"\nseed = 1\nwidth = 160\nheight = 120\nrate_hz = 10.0\n'
        "oracle = true\n",
    )
    lst = listener_factory(router, "cam_t")
    oracles: list[OracleFrame] = []
    sub = lst.session.declare_subscriber(
        KEYS.oracle("fixed", "cam_t"), lambda s: oracles.append(decode(s.payload.to_bytes(), OracleFrame))
    )
    try:
        proc = Proc(["edge-camera", "--config", str(cfg)])
        procs.append(proc)
        wait_for(lambda: lst.n_frames() >= 2 and len(oracles) >= 2, timeout=60,
                 what=f"sim frames and ORACLE samples; output:\n{proc.output}")
    finally:
        sub.undeclare()
    f = lst.frames[0]
    rgb = decode_jpeg(f.jpeg)
    assert rgb.shape == (120, 160, 3) and rgb.std() > 5  # a rendered room, not a blank image
    h = f.header
    assert (h.width, h.height, h.source_kind) == (160, 120, "fixed")
    assert h.intrinsics is not None and h.intrinsics.fx == pytest.approx(80.0)  # 90 deg over 160 px
    assert h.pose_trusted is True and h.T_world_cam is not None
    T = np.asarray(h.T_world_cam)
    assert T[2, 3] > 1.5  # high in a room corner
    assert T[2, 2] < 0  # optical axis (camera z) pointing down
    match = next(o for o in oracles if o.seq == h.seq)
    assert np.allclose(np.asarray(match.T_world_cam_true), T)
    depth = png_to_depth(match.depth_png)
    assert depth.shape == (120, 160) and (depth > 0).mean() > 0.9
    assert len(match.labels) > 5


def test_video_end_without_loop_keeps_process_up_and_router_may_come_later(tmp_path, procs, listener_factory):
    from tests.support.procs import endpoint, free_port, wait_port

    video = tmp_path / "v.avi"
    vw = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for i in range(3):
        vw.write(np.full((48, 64, 3), 40 * i, np.uint8))
    vw.release()
    ep = endpoint(free_port())
    cfg = write_config(tmp_path / "cam.toml", ep, f'type = "video"\npath = "{video}"\nloop = false\n')
    proc = Proc(["edge-camera", "--config", str(cfg)])
    procs.append(proc)
    # No router yet: the camera keeps retrying instead of exiting.
    wait_for(lambda: "cannot open a Zenoh session" in proc.output, timeout=30, what=f"a retry message:\n{proc.output}")
    assert proc.alive()
    router = Proc(["router", "--listen", ep])
    procs.append(router)
    wait_port(int(ep.rsplit(":", 1)[1]))
    lst = listener_factory(ep, "cam_t")
    # Every frame is accounted for: sent, or put before the listener's subscription reached the router
    # (counted undelivered: the camera and the listener connect at the same moment).
    wait_for(lambda: any(s.last_error and "end of video" in s.last_error and
                         s.counters.get("frames_sent", 0) + s.counters.get("frames_undelivered", 0) == 3
                         and s.counters.get("frames_sent", 0) >= 1 for s in list(lst.statuses)),
             timeout=30, what=f"Status: 3 frames then end of video:\n{proc.output}")
    assert proc.alive()
    proc.signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0


def test_recorded_source_sends_its_poses_with_their_accuracy_once(tmp_path, router, procs, listener_factory):
    from edge_camera.pose_accuracy import pose_covariance
    from tests.support.recorded import pose_of, write_sequence

    seq = write_sequence(tmp_path / "seq", n=3, meta={"rate_hz": 20, "pose_sigma_trans_m": 0.05,
                                                      "pose_sigma_rot_deg": 2.0})
    cfg = write_config(tmp_path / "cam.toml", router, f'type = "recorded"\npath = "{seq}"\n')
    lst = listener_factory(router, "cam_t")
    proc = Proc(["edge-camera", "--config", str(cfg)])
    procs.append(proc)

    def ended_without_replay(min_errors: int) -> bool:
        return any(s.last_error and "end of recording" in s.last_error
                   and s.counters.get("frames_sent", 0) + s.counters.get("frames_undelivered", 0) == 3
                   and s.counters.get("frames_sent", 0) >= 1 and s.counters.get("source_errors", 0) >= min_errors
                   for s in list(lst.statuses))

    wait_for(lambda: ended_without_replay(1), timeout=30, what=f"3 frames then end of recording:\n{proc.output}")
    # Reopened after the end (back-off 0.1..0.3 s) and told the end again, never replayed.
    wait_for(lambda: ended_without_replay(3), timeout=30, what=f"the end reported again, no replay:\n{proc.output}")
    assert proc.alive()
    frames = list(lst.frames)
    assert frames and all(f.header.seq < 3 for f in frames)
    for f in frames:
        h = f.header
        assert (h.source_kind, h.pose_trusted, h.width, h.height) == ("fixed", False, 160, 120)
        assert np.allclose(np.asarray(h.T_world_cam), pose_of(h.seq), atol=1e-8)
        assert np.array_equal(np.asarray(h.pose_covariance), pose_covariance(0.05, 2.0))
        assert h.intrinsics.fx == pytest.approx(50.0 * 5) and h.intrinsics.width == 160
    proc.signal(signal.SIGTERM)
    assert proc.wait(timeout=15) == 0


class MjpegServer:
    """An HTTP MJPEG stream on 127.0.0.1 (multipart/x-mixed-replace), like an IP camera's; stop() drops it."""

    def __init__(self, port: int) -> None:
        import threading
        import time
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

        jpg = cv2.imencode(".jpg", np.full((48, 64, 3), 120, np.uint8))[1].tobytes()
        part = b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(jpg) + jpg + b"\r\n"
        self.alive = True
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:
                pass

            def do_GET(self) -> None:  # noqa: N802 - http.server's name
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    while server.alive:
                        self.wfile.write(part)
                        time.sleep(0.05)
                except OSError:
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.httpd.daemon_threads = True
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def stop(self) -> None:
        self.alive = False
        self.httpd.shutdown()
        self.httpd.server_close()


def test_stream_that_goes_away_and_comes_back_recovers_without_a_restart(tmp_path, router, procs, listener_factory):
    from tests.support.procs import free_port

    port = free_port()
    server = MjpegServer(port)
    source = (f'type = "stream"\nurl = "http://127.0.0.1:{port}/stream.mjpg"\nopen_timeout_s = 2.0\n'
              'read_timeout_s = 2.0\n')
    cfg = write_config(tmp_path / "cam.toml", router, source)
    lst = listener_factory(router, "cam_t")
    proc = Proc(["edge-camera", "--config", str(cfg)])
    procs.append(proc)
    try:
        wait_for(lambda: lst.n_frames() >= 3, timeout=30, what=f"first frames; output:\n{proc.output}")
        server.stop()  # the camera's stream goes away
        wait_for(lambda: any(s.state == "degraded" and s.counters.get("source_errors", 0) >= 1
                             for s in list(lst.statuses)), timeout=30, what=f"degraded Status:\n{proc.output}")
        n_before = lst.n_frames()
        server = MjpegServer(port)  # back on the same URL
        wait_for(lambda: lst.n_frames() >= n_before + 3, timeout=30, what=f"frames again:\n{proc.output}")
        wait_for(lambda: any(s.counters.get("reconnects", 0) >= 1 and s.state == "ok" for s in list(lst.statuses)),
                 timeout=10, what="Status ok after reconnecting")
        assert proc.alive()
    finally:
        server.stop()
