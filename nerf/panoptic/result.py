"""A window's trained panoptic part (PanopticResult) and its checkpoint: `state()` to save, `load_panoptic`
to load."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from nerf.config import PanopticConfig, config_from_state
from nerf.fields import param_count
from nerf.model import NerfModel
from nerf.panoptic.assignment import SlotWindow
from nerf.panoptic.heads import PanopticField
from nerf.panoptic.samples import panoptic_field


@dataclass
class PanopticResult:
    field: PanopticField
    cfg: PanopticConfig
    slot_window: SlotWindow | None
    n_slots: int
    steps: int
    fit_s: float
    params: int
    history: list[dict] = field(default_factory=list)
    assignments: int = 0
    """segment-to-slot assignments made."""
    overflow_segments: int = 0
    """segments that found no free slot in their frame (more segments than slots)."""
    instances_skipped: bool = False
    """the window's training frames had no thing detection: a semantic-only phase of cfg.stuff_only_steps ran."""
    frames_without_things: int = 0
    """frame draws whose assignment was skipped because the frame has no thing segment."""
    frames_assigned: int = 0
    """frame draws whose thing segments were assigned to slots."""
    assign_s: float = 0.0
    """wall time of the assignments (costs, ID window, slot memory, linear_sum_assignment)."""

    def state(self) -> dict:
        return {"cfg": asdict(self.cfg), "field": self.field.state_dict(), "n_slots": self.n_slots,
                "slot_window": asdict(self.slot_window) if self.slot_window else None}


def load_panoptic(state: dict, model: NerfModel, device: str = "cpu") -> PanopticResult:
    """PanopticResult (field and settings only) from PanopticResult.state() (a checkpoint may carry slot
    centres of an earlier version: they are not used)."""
    cfg = config_from_state(PanopticConfig, state["cfg"])
    pfield = panoptic_field(model, cfg, state["n_slots"]).to(device)
    pfield.load_state_dict(state["field"])
    sw = SlotWindow(**state["slot_window"]) if state.get("slot_window") else None
    return PanopticResult(pfield, cfg, sw, state["n_slots"], 0, 0.0, param_count(pfield))
