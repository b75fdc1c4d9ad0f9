"""nerf_fit's settings: every NerfConfig setting can be set over the preset with --set, an unset one keeps
the preset's value, and the settings are documented; render_scale is checked."""
import dataclasses

import pytest

from nerf.config import NerfConfig, preset
from pipeline import config as cfgmod
from stages import nerf_fit


def resolved(*items: str) -> nerf_fit.Config:
    return cfgmod.build(nerf_fit.Config, cfgmod.parse_set(list(items)).get("nerf_fit", {}), "nerf_fit")


def test_unset_model_settings_keep_the_preset():
    for name in ("cpu", "S"):
        cfg = resolved(f"nerf_fit.preset={name}", "nerf_fit.seed=3", "nerf_fit.refine_poses=false")
        assert nerf_fit.model_config(cfg) == preset(name, seed=3, refine_poses=False)


def test_every_model_setting_can_be_set_over_the_preset():
    own = {"preset", "refine_poses", "seed"}
    settable = {f.name for f in dataclasses.fields(NerfConfig)} - own
    assert {f.name for f in dataclasses.fields(nerf_fit.Config().model)} == settable
    cfg = resolved("nerf_fit.preset=S", "nerf_fit.model.steps=7", "nerf_fit.model.depth_loss_weight=0",
                   "nerf_fit.model.skip_empty=false", "nerf_fit.model.field_kind=mlp_pe",
                   "nerf_fit.model.edge_ray_share=0.5")
    m = nerf_fit.model_config(cfg)
    assert (m.steps, m.depth_loss_weight, m.skip_empty, m.field_kind, m.edge_ray_share) == (7, 0.0, False, "mlp_pe", 0.5)
    assert m.n_levels == preset("S").n_levels                         # the rest is still the preset's
    assert isinstance(m.steps, int) and isinstance(m.depth_loss_weight, float)


def test_a_bad_model_setting_is_a_clear_error():
    with pytest.raises(cfgmod.ConfigError, match="valid keys"):
        resolved("nerf_fit.model.no_such_setting=1")
    with pytest.raises(cfgmod.ConfigError, match="field_kind"):
        resolved("nerf_fit.model.field_kind=voxels")
    with pytest.raises(cfgmod.ConfigError, match="steps"):
        resolved("nerf_fit.model.steps=many")


def test_model_settings_carry_the_preset_settings_docs():
    docs = cfgmod.field_docs(type(nerf_fit.Config().model))
    assert docs["steps"] == cfgmod.field_docs(NerfConfig)["steps"] and docs["edge_ray_share"]
    lines = cfgmod.describe("nerf_fit", nerf_fit.Config)
    assert any(line.startswith("nerf_fit.model.steps = None    # ") for line in lines)


@pytest.mark.parametrize("bad", [-0.5, 1.5])
def test_render_scale_outside_0_1_is_refused(bad):
    with pytest.raises(ValueError, match="render_scale must be in"):
        nerf_fit.Config(render_scale=bad)


def test_render_scale_is_automatic_by_default():
    assert nerf_fit.Config().render_scale == 0


@pytest.mark.parametrize("name,width", [("cpu", 32), ("S", 64), ("L", 64)])
def test_the_decoders_take_the_presets_width_and_the_heads_their_own(name, width):
    """The cpu preset's density and colour decoders are 32 wide (a third of a CPU training step is in them),
    the GPU presets keep 64; the panoptic heads take nerf_fit.panoptic.hidden at every preset."""
    from types import SimpleNamespace

    import torch

    from nerf.config import PanopticConfig
    from nerf.fields.permuto import RadianceField
    from nerf.panoptic.samples import panoptic_field

    def widths(*nets) -> list[int]:
        return [m.out_features for net in nets for m in list(net)[:-1] if isinstance(m, torch.nn.Linear)]

    cfg = preset(name, log2_capacity=10, log2_capacity_delta=8)
    field = RadianceField(cfg, scene_scale_m=1.0)
    assert widths(field.density_net, field.color_net) == [width] * 2
    for head_width in (PanopticConfig().hidden, 48):
        heads = panoptic_field(SimpleNamespace(cfg=cfg, field=field), PanopticConfig(hidden=head_width), n_slots=4)
        assert widths(heads.semantic, heads.instance) == [head_width] * 5    # 2 + 3 hidden layers
    assert resolved("nerf_fit.panoptic.hidden=48").panoptic.hidden == 48
