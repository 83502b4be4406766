"""The daemon on the simulated cell: real ur_rtde client -> loopback UR simulator, the gate host
driver -> MCU simulator on a pty, camera fed from a dataset. The model is the scripted fake
(grey level -> class), so these tests check the wiring, not a bundle's accuracy."""

from __future__ import annotations

import numpy as np
import pytest

from cell_fakes import FakeEvidence, FakeModel
from vs2t_edge.runtime.dataset import SensorGeometry, write_dataset_meta, write_fabric, write_fabric_index
from vs2t_edge.runtime.daemon import run_daemon
from vs2t_edge.runtime.recording import record_session
from vs2t_edge.runtime.replay import ReplayFile, run_replay
from vs2t_edge.sim.scene import SimulatedCell, item_stream, scene_config_yaml, write_scene_config

GREY = {"denim": 50, "silk": 60, "wool": 70, "tweed": 100}  # tweed: off-scene, votes for nothing
CLASSES = ["denim", "silk", "wool"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ds")
    geo = SensorGeometry(frame_width_px=64, frame_height_px=48, camera_image_px=80)
    write_dataset_meta(root, geo, {"made_by": "test_cell_sim"})
    rng = np.random.default_rng(0)
    rows = []
    from vs2t_edge.runtime.dataset import press_grid_mm

    grid = press_grid_mm(3, 3, 20.0, 20.0)
    for i, (name, grey) in enumerate(GREY.items()):
        attrs = [1, 0] * 6 + [int(v) for v in rng.integers(0, 2, 12)]  # first six pairs exclusive
        rows.append((f"f{i}", name, attrs))
        presses = [(np.full((48, 64, 3), grey, np.uint8), x, y, 15.0) for x, y in grid]
        write_fabric(root, f"f{i}", name, attrs, np.full((80, 80, 3), 128, np.uint8),
                     np.full((48, 64, 3), 120, np.uint8), presses)
    write_fabric_index(root, rows)
    return root


def scene_cfg(tmp_path, dataset, host):
    data = scene_config_yaml(bundle=tmp_path / "bundle", dataset=dataset, journal=tmp_path / "journal.jsonl",
                             fabrics=[("denim", "touched", 1), ("silk", "touched", 2), ("wool", "untouched", 3)],
                             arm_host=host, confidence=0.95, max_presses=3)
    return write_scene_config(tmp_path / "cell.yaml", data)


@pytest.mark.slow
def test_daemon_sorts_a_stream_on_the_simulated_cell(tmp_path, dataset):
    pytest.importorskip("rtde_control")
    from vs2t_edge.runtime.dataset import load_dataset

    items = item_stream(load_dataset(dataset), ["denim", "silk", "wool", "tweed"], 4, seed=1)
    with SimulatedCell(dataset, items, arm_kind="ursim", gate_kind="pty") as cell:
        cfg = scene_cfg(tmp_path, dataset, cell.arm_host)
        code = run_daemon(cfg, model=FakeModel({v: k for k, v in GREY.items() if k in CLASSES}, CLASSES),
                          camera=cell.camera, arm=cell.arm, gate=cell.gate, items=cell.source,
                          evidence_factory=lambda: FakeEvidence(CLASSES, 0.95, 3), install_signals=False,
                          stop_when=cell.source.exhausted, log=lambda m: None)
    assert code == 0
    from vs2t_edge.runtime.journal import read_records

    finals = [r for r in read_records(tmp_path / "journal.jsonl") if r["type"] == "final"]
    name_of = {f"f{i}": name for i, name in enumerate(GREY)}  # items carry the fabric id, as bundles name classes
    truth = {it.id: name_of[it.truth] for it in items}
    assert len(finals) == 4
    for f in finals:
        t = truth[f["item_id"]]
        assert f["outcome"] == "sorted"
        assert f["label"] == (t if t in CLASSES else "unknown")
        assert f["bin"] == {"denim": 1, "silk": 2, "wool": 3}.get(t, 0)


@pytest.mark.slow
def test_simulated_session_with_a_protective_stop_records_and_replays(tmp_path, dataset):
    pytest.importorskip("rtde_control")
    from vs2t_edge.runtime.dataset import load_dataset

    items = item_stream(load_dataset(dataset), ["denim", "wool", "tweed"], 3, seed=2)
    with SimulatedCell(dataset, items, arm_kind="ursim", gate_kind="pty") as cell:
        cfg = scene_cfg(tmp_path, dataset, cell.arm_host)
        cell.schedule_fault(item_index=1, press_number=2, kind="protective_stop")
        model = FakeModel({v: k for k, v in GREY.items() if k in CLASSES}, CLASSES, strength=1.0)
        out = record_session(cfg, tmp_path / "stop.replay", model=model, camera=cell.camera, arm=cell.arm,
                             gate=cell.gate, items=cell.source, evidence_factory=lambda: FakeEvidence(CLASSES, 0.95, 3),
                             operator_clear=cell.operator_clear)
    rf = ReplayFile.open(out)
    kinds = [d.get("kind") for d in rf.index["decisions"] if d["type"] == "fault"]
    assert kinds == ["protective_stop"]
    finals = [d for d in rf.index["decisions"] if d["type"] == "final"]
    assert [f["outcome"] for f in finals] == ["sorted", "rejected_fault", "sorted"]
    press = next(e for e in rf.index["events"] if e["dev"] == "arm" and e["call"] == "press" and "result" in e)
    assert press["result"]["force_n"] == pytest.approx(15.0, abs=1.0)  # telemetry from the UR simulator
    report = run_replay(out, model=FakeModel({v: k for k, v in GREY.items() if k in CLASSES}, CLASSES, strength=1.0),
                        evidence_factory=lambda: FakeEvidence(CLASSES, 0.95, 3))
    assert report.ok, report.mismatches + [report.diverged]


def test_each_piece_of_a_fabric_shows_presses_no_earlier_piece_showed(tmp_path):
    """Every piece is pressed at the same arm points, but a piece is another region of the cloth:
    the simulated camera shows the nearest recorded press no earlier piece of the fabric showed
    (else what a labelled piece taught would be tested on its own frames), never one press twice
    within a piece, and once the fabric's presses run out, presses an earlier piece showed."""
    from types import SimpleNamespace

    from vs2t_edge.runtime.dataset import load_dataset
    from vs2t_edge.sim.scene import DatasetFrames, SceneItems, SimItem, make_reference_world

    ds = load_dataset(make_reference_world(tmp_path / "ds", seed=0, progress=False))
    fabric = ds.fabrics[1]
    points = [(p.x_mm, p.y_mm) for p in fabric.presses[:3]]
    items = SceneItems([SimItem(f"piece-{k}", fabric.id, fabric.id) for k in range(4)])
    arm = SimpleNamespace(pressed=True, target=None)
    frames = DatasetFrames(ds, items, arm)
    shown = []
    for _ in range(4):
        items.index += 1
        for point in points:
            arm.target = point
            frames()
        shown.append([frames._shown[(items.current.id, pt)] for pt in points])
    assert len(fabric.presses) == 9
    assert shown[0] == [0, 1, 2]  # the first piece: the presses at the arm's points
    assert not set(shown[1]) & set(shown[0]) and not set(shown[2]) & (set(shown[0]) | set(shown[1]))
    assert all(len(set(s)) == 3 for s in shown)
    assert set(shown[3]) <= set(shown[0]) | set(shown[1]) | set(shown[2])  # 9 presses, 12 asked: reused
