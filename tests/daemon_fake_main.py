"""Run the real daemon (runtime/daemon.py) in a subprocess with fake devices and a fake model.

Used by tests/test_daemon.py: ``python tests/daemon_fake_main.py CONFIG [--score-delay-s S]``.
The model and devices are the in-test fakes; everything else - signals, sd_notify, journal,
the loop - is the production code path.

``--record OUT`` runs `vs2t-edge record --config CONFIG --out OUT` instead (tests/test_replay.py),
its bundle and devices swapped for the same fakes: the CLI's signal handling and saving are real.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

from cell_fakes import FakeEvidence, FakeModel, ScriptedCamera  # noqa: E402
from vs2t_edge.sim.fake_devices import FakeArm  # noqa: E402
from vs2t_edge.runtime.config import load_config  # noqa: E402
from vs2t_edge.runtime.daemon import run_daemon  # noqa: E402
from vs2t_edge.sim.fake_devices import FakeGate  # noqa: E402


class SlowModel(FakeModel):
    def __init__(self, *a, delay_s=0.0, **k):
        super().__init__(*a, **k)
        self.delay_s = delay_s

    def score_press(self, frame):
        time.sleep(self.delay_s)
        return super().score_press(frame)


class SlowGate(FakeGate):
    """A gate whose ack takes ``delay_s``: holds the daemon between its pre-sort and final records."""

    def __init__(self, *a, delay_s=0.0, **k):
        super().__init__(*a, **k)
        self.delay_s = delay_s

    def sort(self, bin_index):
        time.sleep(self.delay_s)
        return super().sort(bin_index)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("config")
    ap.add_argument("--score-delay-s", type=float, default=0.05)
    ap.add_argument("--load-delay-s", type=float, default=0.0)
    ap.add_argument("--sort-delay-s", type=float, default=0.0)
    ap.add_argument("--record", default=None, help="run `vs2t-edge record --out RECORD` on the fakes")
    a = ap.parse_args()
    cfg = load_config(a.config)
    if a.record:
        return record(a, cfg)
    time.sleep(a.load_delay_s)  # READY must come only after the model is loaded
    arm = FakeArm(config=cfg.arm)
    classes = cfg.scene_classes
    model = SlowModel({50 + 10 * i: c for i, c in enumerate(classes)}, classes, delay_s=a.score_delay_s)
    camera = ScriptedCamera(arm, [50, 60] * 100000)  # alternating votes: items need every press
    return run_daemon(cfg, model=model, camera=camera, arm=arm, gate=SlowGate(delay_s=a.sort_delay_s),
                      evidence_factory=lambda: FakeEvidence(classes, cfg.confidence, cfg.max_presses))


def record(a, cfg) -> int:
    from vs2t_edge import cli
    from vs2t_edge.runtime import wiring

    classes = cfg.scene_classes
    arm = FakeArm(config=cfg.arm)
    wiring.load_model = lambda _cfg: SlowModel({50 + 10 * i: c for i, c in enumerate(classes)}, classes,
                                               delay_s=a.score_delay_s)
    wiring.build_live_devices = lambda _cfg: (ScriptedCamera(arm, [50, 60] * 100000), arm, FakeGate())
    wiring.evidence_factory_for = lambda _cfg, _model=None: (lambda: FakeEvidence(classes, cfg.confidence, cfg.max_presses))
    return cli.main(["record", "--config", a.config, "--out", a.record, "--max-items", "100000"])


if __name__ == "__main__":
    sys.exit(main())
