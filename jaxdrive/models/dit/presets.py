"""Named DiT configurations: the papers' backbones and tiny / small ones for tests and benchmarks.

``preset(name, **overrides)`` returns a checked :class:`DiTConfig`; ``controls=dict(...)``
overrides fields of the controls. Parameter counts (``python -m jaxdrive.models.dit.presets``,
computed with ``jax.eval_shape``) are listed in docs/guides/dit.md.

- ``stdit3-xl/2``: Open-Sora 1.2's STDiT-3 XL/2 (28 layers of a spatial + a temporal block, width
  1152, 16 heads, patch 1x2x2, 4 latent channels, T5-XXL text of 300 tokens, fps).
- ``magicdrive-v2``: STDiT-3 XL/2 with MVDiT cross-view attention on CogVideoX's 16-channel latents
  and all of MagicDrive-V2's controls (text, cameras, trajectory, boxes, map ControlNet).
  The ControlNet depth (``map_blocks``) is not given in the paper; 13 is our choice.
- ``mila``: MiLA (appendix B: "roughly 700M parameters", from Open-Sora 1.1): STDiT-2 layers (28,
  width 1152, 16 heads), spatial attention over all views (eq. 3), cameras and waypoints
  (eq. 1-2), fps, text, clean condition frames.
- ``cogvideox-2b``: CogVideoX-2B's transformer (30 layers, 30 heads of 64, 3D sin-cos positions,
  time embedding 512, T5 text of 226 tokens), the layout of LongDWM's coarse DiT.
- ``longdwm-fine``: CogVideoX-2B with first/last-frame conditions by channel concatenation and
  warp-guided frames (LongDWM [2506.01546v1] sec. 3.2, 3.4).
- ``tiny``, ``tiny-full``, ``tiny-mv`` (every control of the factorized layout), ``small``,
  ``small-full``: for tests and benchmarks.
"""

from __future__ import annotations

from jaxdrive.models.dit.config import Controls, DiTConfig, check_config
from jaxdrive.validate import check_choice

_ALL_CONTROLS = Controls(
    text="embeddings",
    fps=True,
    camera=True,
    waypoints=True,
    trajectory=True,
    boxes=True,
    map=True,
    map_blocks=1,
    cond_frames="replace",
    warp=True,
    map_hidden=16,
    fourier_freqs=4,
)

_STDIT3 = DiTConfig(
    layout="factorized",
    block="stdit3",
    depth=28,
    heads=16,
    head_dim=72,
    in_channels=4,
    text_dim=4096,
    text_len=300,
    controls=Controls(fps=True),
)

_COGVIDEOX_2B = DiTConfig(
    layout="full",
    depth=30,
    heads=30,
    head_dim=64,
    in_channels=16,
    patch=(1, 2, 2),
    positions="sincos",
    spatial_interpolation_scale=1.875,
    time_embed_dim=512,
    time_freq_dim=1920,
    text_dim=4096,
    text_len=226,
    qk_norm="layer",
    norm_eps=1e-5,
    controls=Controls(text_null=False),
)

PRESETS: dict[str, DiTConfig] = {
    "stdit3-xl/2": _STDIT3,
    "magicdrive-v2": _STDIT3.replace(
        multiview="cross_view",
        in_channels=16,
        controls=dict(camera=True, trajectory=True, boxes=True, map=True, map_blocks=13),
    ),
    "mila": _STDIT3.replace(block="stdit2", controls=dict(camera=True, waypoints=True, cond_frames="replace")),
    "cogvideox-2b": _COGVIDEOX_2B,
    "longdwm-fine": _COGVIDEOX_2B.replace(controls=dict(cond_frames="concat", warp=True)),
    "tiny": DiTConfig(
        depth=2,
        heads=4,
        head_dim=16,
        in_channels=4,
        text_dim=32,
        text_len=8,
        time_freq_dim=64,
        controls=Controls(fps=True),
    ),
    "tiny-full": DiTConfig(
        layout="full",
        depth=2,
        heads=4,
        head_dim=16,
        in_channels=4,
        text_dim=32,
        text_len=8,
        time_embed_dim=32,
        time_freq_dim=64,
        qk_norm="layer",
        controls=Controls(fps=True),
    ),
    "tiny-mv": DiTConfig(
        depth=2,
        heads=4,
        head_dim=16,
        in_channels=4,
        text_dim=32,
        text_len=8,
        time_freq_dim=64,
        multiview="cross_view",
        controls=_ALL_CONTROLS,
        htft_layers=(0,),
    ),
    "small": DiTConfig(
        depth=4, heads=8, head_dim=32, in_channels=16, text_dim=256, text_len=32, controls=Controls(fps=True)
    ),
    "small-full": DiTConfig(
        layout="full",
        depth=4,
        heads=8,
        head_dim=32,
        in_channels=16,
        text_dim=256,
        text_len=32,
        time_embed_dim=128,
        qk_norm="layer",
        controls=Controls(fps=True),
    ),
}


def preset(name: str, **overrides) -> DiTConfig:
    """The preset ``name`` with ``overrides`` applied (``ValueError`` for an unknown name)."""
    check_choice("name", name, sorted(PRESETS))
    cfg = PRESETS[name]
    return cfg.replace(**overrides) if overrides else check_config(cfg)


def main() -> None:
    """Print each preset's parameter count (eval_shape, nothing allocated)."""
    from jaxdrive.models.dit.model import param_count

    for name in PRESETS:
        print(f"{name:16s} {param_count(PRESETS[name]):>15,d}")


if __name__ == "__main__":
    main()
