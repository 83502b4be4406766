"""The daemon as a real subprocess: sd_notify on a test NOTIFY_SOCKET, SIGTERM, restart recovery."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from vs2t_edge.runtime.journal import read_records
from vs2t_edge.sim.scene import fake_cell_yaml

HERE = Path(__file__).parent
# the fake models and the committed test bundle have no scene model: the config opts in to them
CONFIG = fake_cell_yaml(fabrics=(("denim", "touched", 1), ("silk", "untouched", 2)), threads=1,
                        evidence={"confidence": 0.95, "max_presses": 4, "without_scene_model": "allow"},
                        watchdog={"wait_item_timeout_s": 0.05})


def start(tmp_path, *extra, env_extra=None):
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(CONFIG)
    sock_path = str(tmp_path / "notify.sock")
    server = notify_server(sock_path, timeout_s=20)
    env = dict(os.environ, NOTIFY_SOCKET=sock_path, WATCHDOG_USEC="400000", PYTHONUNBUFFERED="1")
    env.pop("WATCHDOG_PID", None)
    env.update(env_extra or {})
    proc = subprocess.Popen([sys.executable, str(HERE / "daemon_fake_main.py"), str(cfg), *extra], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, server, tmp_path / "state" / "journal.jsonl"


def notify_server(sock_path: str, timeout_s: float) -> socket.socket:
    """The NOTIFY_SOCKET end systemd would hold: a bound datagram socket."""
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(sock_path)
    server.settimeout(timeout_s)
    return server


def drain(server, quiet_s=0.2) -> list[str]:
    """Every message still queued (or arriving within ``quiet_s`` of the last one)."""
    server.settimeout(quiet_s)
    msgs = []
    try:
        while True:
            msgs.append(server.recv(4096).decode())
    except socket.timeout:
        return msgs


def receive_until(server, pred, limit_s=20.0):
    got = []
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        msg = server.recv(4096).decode()
        got.append(msg)
        if pred(msg):
            return got
    raise AssertionError(f"never saw the expected message; got {got}")


def test_ready_watchdog_status_then_graceful_sigterm(tmp_path):
    proc, server, journal = start(tmp_path, "--load-delay-s", "0.3")
    try:
        msgs = receive_until(server, lambda m: m.startswith("READY=1"))
        assert any(m.startswith("STATUS=loading bundle") for m in msgs[:-1])  # status before READY
        msgs += receive_until(server, lambda m: "pressing" in m)
        msgs += receive_until(server, lambda m: m == "WATCHDOG=1")
        # let a few items go by, then stop in the middle of one
        receive_until(server, lambda m: "-> bin" in m)
        receive_until(server, lambda m: "pressing" in m)
        proc.send_signal(signal.SIGTERM)
        tail = receive_until(server, lambda m: m.startswith("STOPPING=1") and "items" in m)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        server.close()
    assert proc.returncode == 0, err
    recs = read_records(journal)
    types = [r["type"] for r in recs]
    assert types[0] == "start" and types[-1] == "stop" and recs[-1]["reason"] == "SIGTERM"
    finals = [r for r in recs if r["type"] == "final"]
    assert finals and finals[-1]["outcome"] == "aborted" and finals[-1]["bin"] == 0
    items = {r["item"] for r in recs if r["type"] == "item"}
    assert items == {r["item"] for r in finals}  # exactly one final per item
    assert any(m.startswith("STOPPING=1") for m in tail)
    assert "SIGTERM: finishing safely" in err


def test_restart_after_kill_resolves_the_open_item(tmp_path):
    # The gate takes 30 s to ack, so the daemon sits between its pre-sort record and the final
    # one until it is killed: the kill always lands in the window this test is about.
    proc, server, journal = start(tmp_path, "--sort-delay-s", "30")
    try:
        receive_until(server, lambda m: m.startswith("READY=1"))
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            recs = read_records(journal)
            if recs and recs[-1]["type"] == "pre_sort":
                break
            time.sleep(0.01)
        else:
            raise AssertionError(f"no pre-sort record within 30 s: {[r['type'] for r in read_records(journal)]}")
        proc.kill()  # kill -9: no chance to write the final record
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        server.close()
    recs = read_records(journal)
    open_items = {r["item"] for r in recs if r["type"] == "pre_sort"} - {r["item"] for r in recs if r["type"] == "final"}
    assert len(open_items) == 1, [r["type"] for r in recs]
    (tmp_path / "notify.sock").unlink()
    proc, server, journal = start(tmp_path)
    try:
        receive_until(server, lambda m: m.startswith("READY=1"))
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        server.close()
    recs = read_records(journal)
    for item in open_items:
        f = [r for r in recs if r["type"] == "final" and r["item"] == item]
        assert len(f) == 1 and f[0]["outcome"] == "unknown_outcome" and f[0]["bin"] == 0
    started = {r["item"] for r in recs if r["type"] == "item"}
    finals = [r["item"] for r in recs if r["type"] == "final"]
    assert sorted(finals) == sorted(started)  # every item has exactly one final record


def test_bad_bundle_exits_2_without_ready(tmp_path):
    """The `run` verb on a config whose bundle is missing: no READY, exit 2, reason on stderr."""
    cfg = tmp_path / "cell.yaml"
    cfg.write_text(CONFIG)
    sock_path = str(tmp_path / "n.sock")
    server = notify_server(sock_path, timeout_s=0.2)
    env = dict(os.environ, NOTIFY_SOCKET=sock_path)
    proc = subprocess.run([sys.executable, "-m", "vs2t_edge", "run", "--config", str(cfg)], env=env,
                          capture_output=True, text=True, timeout=60)
    msgs = drain(server)
    server.close()
    assert proc.returncode == 2, proc.stderr
    assert "bundle" in proc.stderr and not any(m.startswith("READY=1") for m in msgs)


def test_clear_fault_command(tmp_path, capsys):
    from vs2t_edge.cli import main

    cfg = tmp_path / "cell.yaml"
    cfg.write_text(CONFIG)
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "FAULT").write_text("item 3: gate jam\n")
    assert main(["run", "--config", str(cfg), "--clear-fault"]) == 0
    assert "gate jam" in capsys.readouterr().out
    assert not (tmp_path / "state" / "FAULT").exists()


@pytest.mark.hardware(needs="the real cell (VS2T_CELL_CONFIG, default /etc/vs2t-edge/cell.yaml; service stopped)")
def test_live_cell_sorts_one_piece():
    """On the real cell: VS2T_HARDWARE=1 VS2T_CELL_CONFIG=/etc/vs2t-edge/cell.yaml (service stopped)."""
    cfg = os.environ.get("VS2T_CELL_CONFIG", "/etc/vs2t-edge/cell.yaml")
    proc = subprocess.run([sys.executable, "-m", "vs2t_edge", "run", "--config", cfg, "--max-items", "1"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


def test_full_disk_at_start_exits_2_in_words(tmp_path, monkeypatch):
    """The journal cannot take the start record (ENOSPC): no traceback, exit 2, the reason in
    words, the gate left at reject and every device let go - nothing moves without a journal."""
    from cell_fakes import FakeModel, ScriptedCamera
    from vs2t_edge.runtime import journal as jmod
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.runtime.notify import Notifier

    cfg_path = tmp_path / "cell.yaml"
    cfg_path.write_text(CONFIG)
    cfg = load_config(cfg_path)
    real_append = jmod.Journal.append

    def append(self, rec):
        if rec.get("type") == "start":
            raise jmod.JournalWriteError(f"journal {self.path}: write failed: [Errno 28] No space left on device",
                                         28, cut_back=True)
        return real_append(self, rec)

    monkeypatch.setattr(jmod.Journal, "append", append)
    arm, gate, logged = FakeArm(config=cfg.arm), FakeGate(), []
    code = run_daemon(cfg, model=FakeModel({50: "denim"}, cfg.scene_classes), camera=ScriptedCamera(arm, [50]),
                      arm=arm, gate=gate, notifier=Notifier(""), max_items=1, install_signals=False,
                      log=logged.append)
    assert code == 2
    text = "\n".join(logged)
    assert "cannot write the start record" in text and "No space left" in text, text
    assert gate.to_reject_calls >= 1 and gate.sorted == []
    assert not gate._connected and not arm.connected


def test_a_fault_file_the_service_cannot_write_stops_the_start_in_words(tmp_path):
    """A fault_file outside the unit's ReadWritePaths (EROFS) or in a missing folder: a fault could
    not be latched durably, so the service refuses to start, before any device moves."""
    from cell_fakes import FakeModel, ScriptedCamera
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

    cfg_path = tmp_path / "cell.yaml"
    cfg_path.write_text(fake_cell_yaml(fabrics=(("denim", "touched", 1), ("silk", "untouched", 2)), threads=1,
                                       evidence={"confidence": 0.95, "max_presses": 4, "without_scene_model": "allow"},
                                       fault_file="no-such-folder/FAULT"))
    cfg = load_config(cfg_path)
    arm, gate, logged = FakeArm(config=cfg.arm), FakeGate(), []
    code = run_daemon(cfg, model=FakeModel({50: "denim"}, cfg.scene_classes), camera=ScriptedCamera(arm, [50]),
                      arm=arm, gate=gate, notifier=Notifier(""), max_items=1, install_signals=False,
                      log=logged.append)
    assert code == 2 and gate.sorted == [] and not arm.connected
    assert any(f"fault file {cfg.fault_file}" in line and "writable" in line for line in logged), logged


def test_a_model_crash_latches_a_fault_and_a_restart_refuses_until_cleared(tmp_path):
    """An onnxruntime RuntimeError mid-item: run_daemon used to re-raise it (no FAULT file; systemd
    restarted the service, which sorted on with no operator). Now the fault latches, the service
    keeps running in fault and stops cleanly (exit 0), and the next start stays latched."""
    from cell_fakes import FakeModel, ScriptedCamera
    from vs2t_edge.sim.fake_devices import FakeArm
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.sim.fake_devices import FakeGate
    from vs2t_edge.runtime.notify import Notifier

    class CrashingModel(FakeModel):
        def score_press(self, frame):
            raise RuntimeError("[ONNXRuntimeError] : 6 : RUNTIME_EXCEPTION : Non-zero status code (injected)")

    cfg_path = tmp_path / "cell.yaml"
    cfg_path.write_text(CONFIG)
    cfg = load_config(cfg_path)

    def start_once(model, logged, stop_when):
        arm, gate = FakeArm(config=cfg.arm), FakeGate()
        code = run_daemon(cfg, model=model, camera=ScriptedCamera(arm, [50] * 10), arm=arm, gate=gate,
                          notifier=Notifier(""), max_items=1, install_signals=False, log=logged.append,
                          stop_when=stop_when)
        return code, arm, gate

    logged: list[str] = []
    code, arm, gate = start_once(CrashingModel({50: "denim"}, cfg.scene_classes), logged, cfg.fault_file.exists)
    assert code == 0
    assert "RuntimeError" in cfg.fault_file.read_text()
    assert any("Traceback" in m for m in logged) and "stop" in arm.calls and gate.sorted == []
    recs = read_records(cfg.journal)
    assert [r["kind"] for r in recs if r["type"] == "fault"] == ["internal"]
    assert [r["outcome"] for r in recs if r["type"] == "final"] == ["rejected_fault"]
    # the restart (systemd's, or the operator's) does not resume on its own
    polls = iter(range(20))
    code, arm, gate = start_once(FakeModel({50: "denim"}, cfg.scene_classes), [],
                                 lambda: next(polls, None) is None)  # 20 turns: one item if not latched
    assert code == 0 and arm.calls.count("press") == 0 and cfg.fault_file.exists()
    assert [r["type"] for r in read_records(cfg.journal)].count("final") == 1


@pytest.mark.parametrize("fabric,declared,bundle_kind", [("f01", "touched", "untouched"),
                                                         ("f04", "untouched", "touched")])
def test_scene_kind_that_disagrees_with_the_bundle_is_refused(tmp_path, fabric, declared, bundle_kind):
    """load_model used to check only that a scene name is some class of the bundle: a zero-shot
    fabric declared touched (or the reverse) started sorting."""
    import yaml

    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.wiring import load_model

    scene = {"reject_bin": 0, "fabrics": [{"name": "f00", "kind": "touched", "bin": 1},
                                          {"name": "f04", "kind": "touched", "bin": 2},
                                          {"name": "f01", "kind": "untouched", "bin": 3}]}
    config = {"bundle": str((HERE / "replays" / "bundle").resolve()), "threads": 1,
              "devices": {"camera": {"kind": "replay", "path": "frames"}, "arm": {"kind": "fake"},
                          "gate": {"kind": "fake"}},
              "scene": scene, "journal": str(tmp_path / "journal.jsonl")}
    (tmp_path / "good.yaml").write_text(yaml.safe_dump(config))
    assert load_model(load_config(tmp_path / "good.yaml")) is not None  # the scene as the bundle has it
    for f in scene["fabrics"]:
        if f["name"] == fabric:
            f["kind"] = declared
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(config))
    with pytest.raises(ValueError) as err:
        load_model(load_config(tmp_path / "bad.yaml"))
    assert f"{fabric} (scene: {declared}, bundle: {bundle_kind})" in str(err.value)
    assert "bad.yaml" in str(err.value)
    # a bundle the caller loaded (replay, recording, the demo) is checked at the start alike
    from cell_fakes import ScriptedCamera
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

    bad = load_config(tmp_path / "bad.yaml")
    arm, gate, logged = FakeArm(config=bad.arm), FakeGate(), []
    code = run_daemon(bad, model=load_model(load_config(tmp_path / "good.yaml")), camera=ScriptedCamera(arm, [50]),
                      arm=arm, gate=gate, notifier=Notifier(""), max_items=1, install_signals=False,
                      log=logged.append)
    assert code == 2 and gate.sorted == [] and not arm.connected
    assert any(f"{fabric} (scene: {declared}, bundle: {bundle_kind})" in line for line in logged), logged


def _run_real_bundle(tmp_path, bundle, *, until_ready: bool):
    """`vs2t-edge run` (the real verb, the real load_model) on a copy of tests/replays/bundle with
    the replayed camera and the in-process arm and gate; the notify socket's messages in order."""
    import json

    import yaml

    ref = json.loads((HERE / "replays" / "touched.replay" / "index.json").read_text())
    config = {"bundle": str(bundle), "threads": 1,
              "devices": {"camera": {"kind": "replay", "path": str((HERE / "replays" / "touched.replay" / "frames"))},
                          "arm": {"kind": "fake"}, "gate": {"kind": "fake"}},
              "scene": ref["config"]["scene"],  # the committed bundle has no scene model: opted in
              "evidence": {**ref["config"]["evidence"], "without_scene_model": "allow"},
              "journal": str(tmp_path / "state" / "journal.jsonl"), "watchdog": {"wait_item_timeout_s": 0.05}}
    (tmp_path / "cell.yaml").write_text(yaml.safe_dump(config))
    sock_path = str(tmp_path / "n.sock")
    server = notify_server(sock_path, timeout_s=60)
    env = dict(os.environ, NOTIFY_SOCKET=sock_path, PYTHONUNBUFFERED="1")
    env.pop("WATCHDOG_USEC", None)
    proc = subprocess.Popen([sys.executable, "-m", "vs2t_edge", "run", "--config", str(tmp_path / "cell.yaml")],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    msgs: list[str] = []
    try:
        if until_ready:
            msgs = receive_until(server, lambda m: m.startswith("READY=1"), limit_s=60)
            proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=60)
        msgs += drain(server)
    finally:
        if proc.poll() is None:
            proc.kill()
        server.close()
    return proc.returncode, msgs, err


def test_ready_comes_only_after_the_real_bundle_is_verified_warm_and_probed(tmp_path):
    """test_ready_watchdog_status_then_graceful_sigterm's fake model cannot show the load order;
    this runs the `run` verb on the committed bundle: READY=1 only after the probe check's line."""
    import shutil

    shutil.copytree(HERE / "replays" / "bundle", tmp_path / "bundle")
    code, msgs, err = _run_real_bundle(tmp_path, tmp_path / "bundle", until_ready=True)
    assert code == 0, err
    probe_at = next(i for i, m in enumerate(msgs) if "probe check passed" in m)
    ready_at = next(i for i, m in enumerate(msgs) if m.startswith("READY=1"))
    assert any(m.startswith("STATUS=loading bundle") for m in msgs[:probe_at])
    assert probe_at < ready_at and sum(m.startswith("READY=1") for m in msgs) == 1
    assert "probe check passed" in err and err.index("probe check passed") < err.index("SIGTERM")
    # the bundle is named by its path, not by its folder's name ("bundle bundle verified")
    assert f"bundle {tmp_path / 'bundle'} verified" in err and "bundle bundle" not in err
    # the start record names the bundle's seal, so a bundle swapped in the same folder is auditable
    import json

    from vs2t_edge.runtime.bundle import SEAL_KEY

    start = next(r for r in read_records(tmp_path / "state" / "journal.jsonl") if r["type"] == "start")
    assert start[SEAL_KEY] == json.loads((tmp_path / "bundle" / "manifest.json").read_text())[SEAL_KEY]


@pytest.mark.parametrize("damage", ["graph_byte_flipped", "probe_expected_off"])
def test_a_damaged_real_bundle_never_sends_ready_and_exits_2(tmp_path, damage):
    import json
    import shutil

    import numpy as np

    from vs2t_edge.runtime.bundle import seal_manifest, sha256_file

    b = tmp_path / "bundle"
    shutil.copytree(HERE / "replays" / "bundle", b)
    if damage == "graph_byte_flipped":  # caught by the hashes, before any session opens
        data = bytearray((b / "heads.onnx").read_bytes())
        data[len(data) // 2] ^= 0x01
        (b / "heads.onnx").write_bytes(bytes(data))
        words = "heads.onnx"
    else:  # hashes re-made to match: only the warm-up's probe run can catch it
        exp = dict(np.load(b / "probe_expected.npz"))
        exp["novelty"] = exp["novelty"] * 1.01
        np.savez(b / "probe_expected.npz", **exp)
        m = json.loads((b / "manifest.json").read_text())
        m["files"]["probe_expected.npz"] = sha256_file(b / "probe_expected.npz")
        (b / "manifest.json").write_text(json.dumps(seal_manifest(m), indent=1))  # the old seal is replaced
        words = "probe check failed: 'novelty'"
    code, msgs, err = _run_real_bundle(tmp_path, b, until_ready=False)
    assert code == 2, err
    assert words in err and not any(m.startswith("READY=1") for m in msgs)
    assert not any("probe check passed" in m for m in msgs)


def test_the_start_record_says_what_the_camera_runs(tmp_path):
    """A UVC camera's accepted settings (pixel format, size, queue, flush) are journaled in the start
    record and logged, so a cell asked for YUYV can be seen running it; a camera that says nothing
    (simulated, replayed) leaves the key out."""
    from cell_fakes import FakeModel, ScriptedCamera
    from vs2t_edge.runtime.config import load_config
    from vs2t_edge.runtime.daemon import run_daemon
    from vs2t_edge.runtime.notify import Notifier
    from vs2t_edge.sim.fake_devices import FakeArm, FakeGate

    for says in (True, False):
        folder = tmp_path / str(says)
        folder.mkdir()
        cfg_path = folder / "cell.yaml"
        cfg_path.write_text(fake_cell_yaml(fabrics=(("denim", "touched", 1), ("silk", "untouched", 2)), threads=1,
                                           evidence={"confidence": 0.95, "max_presses": 4,
                                                     "without_scene_model": "allow"}))
        cfg = load_config(cfg_path)
        arm, gate, logged = FakeArm(config=cfg.arm), FakeGate(), []
        camera = ScriptedCamera(arm, [50])
        if says:
            camera.settings_applied = {"width": 640.0, "height": 480.0, "pixel_format": "YUYV", "yuyv_raw": True,
                                       "flush_frames": 2, "exposure": None}
        code = run_daemon(cfg, model=FakeModel({50: "denim"}, cfg.scene_classes), camera=camera, arm=arm, gate=gate,
                          notifier=Notifier(""), max_items=1, install_signals=False, log=logged.append)
        assert code == 0, logged
        start = next(r for r in read_records(cfg.journal) if r["type"] == "start")
        if says:
            assert start["camera"] == camera.settings_applied
            assert any("camera runs:" in line and "pixel_format YUYV" in line for line in logged), logged
        else:
            assert "camera" not in start and not any("camera runs" in line for line in logged)
