"""What the cell loop needs to know of its job: the scene's bins, the press points, the limits
(runtime/cell.py reads it; a CellConfig gives it via ``SceneSpec.from_config``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass
class SceneSpec:
    """What the loop needs from the config (a CellConfig satisfies it via from_config)."""

    bins: dict[str, int]  # scene class -> bin
    reject_bin: int
    points_mm: list[tuple[float, float]]  # grid points in press order
    max_presses: int
    confidence: float
    item_timeout_s: float = 60.0
    wait_item_timeout_s: float = 1.0
    fault_file: Path | None = None
    bounds: Any = None  # runtime/budget.py StepBounds: device waits the watchdog is fed through
    # score a press while the arm moves on (runtime/press_pipeline.py). Off here, so a loop built
    # by hand (tests, the fault matrix) makes the same device calls whatever the timing; the
    # config's cell.overlap_scoring (default on) sets it for the service.
    overlap_scoring: bool = False

    @classmethod
    def from_config(cls, cfg) -> "SceneSpec":
        from vs2t_edge.runtime.budget import bounds_of

        return cls(bins={f.name: f.bin for f in cfg.fabrics}, reject_bin=cfg.reject_bin,
                   points_mm=cfg.press_points_mm(), max_presses=cfg.max_presses,
                   confidence=cfg.confidence, item_timeout_s=cfg.item_timeout_s,
                   wait_item_timeout_s=cfg.wait_item_timeout_s, fault_file=cfg.fault_file,
                   bounds=bounds_of(cfg.camera, cfg.arm_kind, cfg.arm, cfg.gate),
                   overlap_scoring=cfg.overlap_scoring)

    @property
    def classes(self) -> list[str]:
        return list(self.bins)

    def bin_for(self, label: str) -> int:
        return self.bins.get(label, self.reject_bin)


__all__ = ["SceneSpec"]
