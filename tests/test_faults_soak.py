"""Short soak-style checks (the long soak is `python -m vs2t_edge.sim.soak`)."""

from __future__ import annotations

from vs2t_edge.sim import fault_rig


def run_items(tmp_path, n):
    rig = fault_rig.build_rig(tmp_path, [fault_rig.TRUTHS[i % 4] for i in range(n)])
    fault_rig.run_rig(rig)
    return rig


def test_many_items_one_final_each(tmp_path):
    rig = run_items(tmp_path, 120)
    a = fault_rig.audit(rig.journal_path, {it.id: it.truth for it in rig.pieces.items})
    assert not a["problems"] and len(a["finals"]) == 120


def test_in_memory_state_is_bounded(tmp_path):
    # Journal.records and Cell.results used to keep everything (daemon RSS grew ~1.6 MiB per 1000
    # presses): now bounded windows plus counters over the whole run, the file has the rest.
    seen = []
    rig = fault_rig.build_rig(tmp_path, [fault_rig.TRUTHS[i % 4] for i in range(300)])
    rig.cell.on_item = seen.append
    fault_rig.run_rig(rig)
    assert len(rig.cell.journal.records) < 200 and len(rig.cell.results) < 200
    assert rig.cell.items_done == 300 == len(seen) == sum(rig.cell.outcomes.values())
    assert [r.item.id for r in rig.cell.results] == [r.item.id for r in seen[-len(rig.cell.results):]]
    j = rig.cell.journal
    assert j.counts["final"] == 300 and j.next_item_number() == 301 and not j.unresolved_items()


def test_the_soak_runs_the_real_inference_path_on_the_committed_bundle(tmp_path):
    """--model onnx (the default): the bundle's TactileModel and the real Evidence score the
    replays' recorded frames; the loop's promises hold and the scoring time is measured."""
    from vs2t_edge.runtime.journal import read_records
    from vs2t_edge.sim import soak

    res = soak.soak(40, gate_kind="fake", sample=4, workdir=tmp_path, progress=False)
    assert res["model"].startswith("real inference path: bundle tests/replays/bundle")
    assert not res["problems"] and res["items"] >= 10 and res["presses"] >= 40
    assert res["score_ms_first"] > 0 and res["score_ms_last"] > 0
    pre = [r for r in read_records(tmp_path / "journal.jsonl") if r["type"] == "pre_sort"]
    bundle_classes = {"f00", "f01", "f02", "f04", "f05", "f06", "f08", "f09"}
    scored = [sc for r in pre for sc in r["scores"]]
    assert scored and all(set(sc["log_posterior"]) <= bundle_classes for sc in scored)  # not the grey model's
    assert len({round(sc["novelty"], 6) for sc in scored}) > 5  # the router scored real, varied frames


def test_the_soak_pairs_each_recorded_piece_with_its_own_frames(tmp_path):
    """A recorded piece with no camera grab (it faulted before its reference) must not shift the
    pairing: every later piece keeps its own truth with its own frames, not the next piece's."""
    import json
    import shutil
    from pathlib import Path

    import numpy as np

    from vs2t_edge.runtime.replay_file import ReplayFile
    from vs2t_edge.sim import soak

    src = Path(soak.default_bundle()).parent
    (tmp_path / "bundle").symlink_to(src / "bundle")
    for name in soak.REPLAYS:
        shutil.copytree(src / f"{name}.replay", tmp_path / f"{name}.replay")
    ix_path = tmp_path / "touched.replay" / "index.json"
    ix = json.loads(ix_path.read_text())
    assert [it["truth"] for it in ix["items"]] == ["f04", "f05", "f08"]
    ix["events"] = [ev for ev in ix["events"] if not (ev["item"] == 1 and ev["dev"] == "camera")]
    ix["decisions"] = [d for d in ix["decisions"] if d.get("item_id") != "item-0002"]
    ix_path.write_text(json.dumps(ix))

    rig_kw, truths = soak.onnx_path(tmp_path / "bundle")
    assert truths[:2] == ["f04", "f08"]  # the piece without a grab is left out, not its neighbour's frames
    f08_ref = next(ref for i, ref, _ in ReplayFile.open(tmp_path / "touched.replay").frames_by_item() if i == 2)

    class Arm:
        pressed = False

    class Pieces:
        index = 1

    assert np.array_equal(rig_kw["frames"](Arm(), Pieces())(), f08_ref)
