"""The typed configuration of the diffusion transformer (:mod:`jaxdrive.models.dit`).

``DiTConfig`` describes the backbone (layout, sizes, positions, execution options) and
``Controls`` which driving conditions it takes. Both are frozen dataclasses (hashable, so a config
can be a field of a linen Module); :func:`check_config` validates one and names the field.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import jax.numpy as jnp

from jaxdrive.attention import IMPLS
from jaxdrive.flow.rectified import PREDICTIONS  # the one list of output kinds (pure math, no jaxdrive deps)
from jaxdrive.validate import check_choice, check_positive_int

LAYOUTS = ("factorized", "full")
BLOCKS = ("stdit3", "stdit2")
TEMPORAL = ("on", "off", "zero_init")
MULTIVIEW = ("joint", "cross_view")
QK_NORMS = ("rms", "layer", "none")
POSITIONS = ("rope", "sincos")
REMAT = ("none", "full", "dots", "dots_no_batch")
# Attentions that never communicate run one of these (never ring / ulysses).
LOCAL_IMPLS = ("xla", "blockwise", "cudnn", "splash")
DTYPES = ("float32", "bfloat16", "float16")
OUT_PATCHES = ("disjoint", "overlap")
TEXT_KINDS = ("embeddings", "caption", None)
COND_FRAMES = ("replace", "concat", None)
REFERENCE_FRAME = ("input", "residual", "warp", None)

# Condition names accepted in ``drop`` (classifier-free guidance), as in the data pipeline where
# they overlap ("text", "boxes", "map", "trajectory", "camera").
CONDITIONS = ("text", "fps", "camera", "waypoints", "trajectory", "boxes", "map", "warp", "frame_time")


@dataclass(frozen=True)
class Controls:
    """Which conditions the DiT takes (each off by default except text).

    - ``text``: ``"embeddings"`` (precomputed T5-style ``[B, L, text_dim]`` with a mask),
      ``"caption"`` (token ids of the built-in caption encoder, :mod:`jaxdrive.data.text`) or
      ``None``. ``text_null``: a learned null text for classifier-free guidance (imported CogVideoX
      models have none: their null is the encoder's embedding of the empty prompt).
    - ``fps``: frame rate added to the timestep embedding (Open-Sora).
    - ``camera``: intrinsics + camera-to-ego per view, Fourier + MLP, added to the tokens of that
      view (MiLA [2503.15875v1] eq. 1-2). ``waypoints``: ego waypoints per frame, likewise
      (MiLA [2503.15875v1] eq. 1-2).
    - ``trajectory``: MagicDrive-V2's ego trajectory encoder (relative poses -> temporal
      transformer -> downsampled to latent frames), one cross-attention token per frame.
    - ``boxes``: 3D boxes (MagicDrive-V2): corners Fourier-embedded + class embedding, invisible
      boxes masked, per-box temporal transformer with RoPE, downsampled to latent frames; cross-
      attention tokens per (frame, view). ``box_per_view``: corners in each camera's frame and
      boxes behind / outside a camera masked for that view.
    - ``map``: the BEV map as a ControlNet branch over the first ``map_blocks`` layers.
    - ``layout``: the projected layout canvas (:mod:`jaxdrive.models.dit.layout`, in the style of
      Ctrl-V's and CoGen's layout conditioning): per frame and camera, the boxes' filled
      silhouettes by class (nearest in front), a near-box channel and the BEV map's road classes
      on the visible ground, ray cast with the clip's own cameras at the latent grid
      (``layout_samples`` x ``layout_samples`` rays per latent cell, averaged), two 3x3
      convolutions of ``layout_hidden`` channels, the VAE's temporal alignment, then per token a
      zero-initialised projection added to the tokens. It reads the box inputs (and the BEV map,
      spanning ``layout_bev_range`` metres (x, y), where given) and is dropped with the boxes
      (``drop["boxes"]``), so guidance that drops the boxes drops the layout too; with
      ``boxes=False`` it is the only box pathway.
    - ``cond_frames``: clean condition frames: ``"replace"`` (Open-Sora / MiLA: the given latents
      replace those frames, whose noise level becomes 0) or ``"concat"`` (CogVideoX-I2V / LongDWM:
      ``[cond * mask, mask]`` through a zero-initialised patch embedding added to the tokens).
    - ``reference_frame`` (with ``cond_frames``): ``"input"``: the newest given frame's latents
      are also concatenated to every frame's input (``[ref * given, given]``, through a
      zero-initialised patch embedding), as Stable Video Diffusion (Blattmann et al. 2023, sec.
      4.4) feeds its conditioning frame to every frame. Each token then sees the clean content at
      its own position, so continuing the scene is a local map, where finding the condition frames
      through temporal attention alone takes thousands of steps. ``"residual"``: the same input,
      and the output (``prediction="data"``) is the change from that frame, ``x = ref + out``, as
      GenCast (Price et al. 2024) predicts the residual to the current state: a freshly
      initialised model repeats the last given frame, with all of its detail, and training
      learns the motion. A clip with no given frame gets ``ref = 0``. ``"warp"`` (with ``warp``):
      the reference of every frame is that frame's warped latents (the given frame warped along
      the route, LongDWM [2506.01546v1] sec. 3.4), input as ``[warp, 1]`` and the output its
      correction, ``x = warp + out``: a freshly initialised model gives the warp itself, and
      training learns what the one-depth warp gets wrong (parallax, holes, the traffic). Where
      the warp is dropped (guidance, ``drop["warp"]``) the reference is the newest given frame's,
      as ``"residual"``: the null route holds still.
    - ``warp``: LongDWM's warp-guided frames: warped latents through a trainable patch embedding,
      injected into every layer through zero-initialised projections.
    - ``frame_time``: each frame's time in seconds (``Conditions.frame_times``), so that one clip
      can mix frame rates (MiLA [2503.15875v1] appendix B: 12-fps condition frames, then generated frames at 1-12
      fps). Each latent frame's time relative to the window's first frame (a window cut from a
      long clip means what the same window alone means), Fourier + MLP (MiLA [2503.15875v1] eq. 1), added to
      that frame's tokens (eq. 2). The last projection starts at zero, so a model initialised
      from a run without the control starts unchanged; a dropped or absent ``frame_times`` adds
      nothing (the model without the control).
    """

    text: str | None = "embeddings"
    text_null: bool = True
    fps: bool = False
    camera: bool = False
    waypoints: bool = False
    trajectory: bool = False
    boxes: bool = False
    box_per_view: bool = True
    num_classes: int = 10
    map: bool = False
    map_channels: int = 8
    map_blocks: int = 2
    map_hidden: int = 64
    layout: bool = False
    layout_hidden: int = 32
    layout_samples: int = 2
    layout_bev_range: tuple[float, float] = (100.0, 100.0)
    cond_frames: str | None = None
    reference_frame: str | None = None
    warp: bool = False
    frame_time: bool = False
    fourier_freqs: int = 8
    fourier_temperature: float = 100.0
    encoder_layers: int = 1
    caption_vocab: int = 4096
    caption_layers: int = 2

    def enabled(self) -> tuple[str, ...]:
        """The conditions this DiT takes, by their names in :data:`CONDITIONS` (the one list
        of which controls are on: checks, batch preparation and guidance read it). ``"boxes"``
        names the box inputs and their drop, which both box pathways read (cross-attention with
        ``boxes``, the canvas with ``layout``)."""
        on = {
            "text": self.text is not None,
            "fps": self.fps,
            "camera": self.camera,
            "waypoints": self.waypoints,
            "trajectory": self.trajectory,
            "boxes": self.boxes or self.layout,
            "map": self.map,
            "warp": self.warp,
            "frame_time": self.frame_time,
        }
        return tuple(name for name in CONDITIONS if on[name])


@dataclass(frozen=True)
class DiTConfig:
    """The diffusion transformer.

    Layout ``"factorized"`` (STDiT-3 / MVDiT): ``block`` ``"stdit3"`` (a layer = a spatial block
    + a temporal block, each with self-attention, text cross-attention and MLP; Open-Sora 1.2,
    MagicDrive-V2) or ``"stdit2"`` (a layer = spatial attention, temporal attention,
    cross-attention and MLP under one adaLN; Open-Sora 1.1, on which MiLA builds); ``multiview``
    ``"joint"`` (spatial attention over all views' tokens of a frame, MiLA [2503.15875v1] eq. 3) or
    ``"cross_view"`` (spatial attention per view plus cross-view attention to the views at
    ``neighbor_offsets``, MagicDrive-V2). Layout ``"full"`` (CogVideoX): full 3D attention over
    ``[text; video]`` with expert adaLN, ``positions`` ``"rope"`` or ``"sincos"``.

    Growing (MagicDrive-V2 [2411.13807v3] sec. 4.3 / appendix B, after Open-Sora 1.2): ``temporal`` ``"off"``
    builds the stdit3 layers without their temporal blocks (a spatial-only model, trained on
    images); ``"zero_init"`` adds them with their attention and MLP output projections
    zero-initialised, so each starts as the identity and a spatial-only model's parameters loaded
    into the rest (``train.init_from``) give exactly its outputs; ``"on"``: the usual init.

    Sizes: ``width = heads * head_dim``; ``patch = (pt, ph, pw)``. ``time_embed_dim`` (``None`` =
    width) and ``time_freq_dim`` size the timestep embedding; ``timestep_scale`` maps sigma to the
    embedded timestep (1000: Open-Sora's t and imported CogVideoX models). ``text_len`` is the
    longest text (the learned null text has that many tokens).

    Output: ``prediction`` ``"velocity"`` (the network predicts ``noise - x``) or ``"data"`` (it
    predicts the clean latents, turned into the velocity by
    :func:`jaxdrive.flow.velocity_from_output` with ``max(sigma, prediction_min_sigma)``; Li & He
    2025, JiT). A token of more numbers than the width (``patch_dim > width``) can only learn with
    data prediction: the velocity at high noise is mostly the token's own noise, which a narrower
    network cannot pass through, so that pairing is refused. ``sigma_data`` (0: off; data
    prediction only) preconditions that estimate as EDM does (Karras et al. 2022, eq. 7,
    :func:`jaxdrive.flow.skip_coefficients`): ``x = ref + c_skip (x_t - (1 - sigma) ref) + c_out
    out`` with ``ref`` the reference frame (``controls.reference_frame`` ``"residual"`` or
    ``"warp"``; else 0) and ``sigma_data`` the standard deviation of ``x - ref``. A fresh model is
    then EDM's linear estimate around ``ref`` (``ref`` itself only from pure noise: it samples
    ``ref`` plus noise of that deviation), no longer ``ref``. Without it the network must
    redraw a nearly clean input through its per-token head, whose rank is the width (64 or 128)
    against a token's 192 numbers: its estimate at level 0.03 draws the token grid onto a
    gridless input (docs/results/demo.md); with it, the input passes through at low levels and
    the head adds a correction scaled by ``c_out``. ``final_conv`` (channels; 0: off)
    adds U-ViT's two 3x3 convolutions after the unpatchify (Bao et al. 2023, sec. 3.1), over the
    output, the input and the given frame: without them each token's output is a linear map of its
    own hidden state, and a narrow model's frames show the token grid as blocks.
    ``out_patches``: ``"disjoint"`` (each token paints its own ``ph x pw`` footprint, as every
    imported model) or ``"overlap"`` (each paints ``2 ph x 2 pw`` centred on it, tent-weighted and
    summed with its neighbours', :func:`jaxdrive.models.dit.embed.unpatchify_overlap`: no seam on
    the token grid's lines; even ``ph`` and ``pw``, 4x the output projection).

    Boxes: ``box_range`` (metres) divides the box corners before their Fourier features
    (``controls.boxes``), so a corner at the edge of the range is 1: MagicDrive min-max normalises
    its box corners before its Fourier embedder (``XYZ_MIN`` / ``XYZ_RANGE`` of its
    ``bbox_embedder``); jaxdrive's default is the +-51.2 m of the nuScenes detection range its
    data follows, one scale for x, y, z and for corners in a camera's frame (``box_per_view``).
    ``None`` keeps raw metres (runs trained before the normalisation: their saved config lacks
    the field and loads with ``None``, see :func:`jaxdrive.train.common.load_run_config`).
    ``box_freqs``: the Fourier frequency count of the corners, ``temperature^(i / n)``, ``i < n``
    (:func:`jaxdrive.models.embeddings.fourier_features`; with the default 8 and temperature 100
    the highest is ~56 rad per unit, a ~6 m wavelength at the default range, where it was ~0.1 m
    on raw metres).

    Execution: ``dtype`` (compute; params are float32), ``remat`` (``"none"``, ``"full"``,
    ``"dots"``, ``"dots_no_batch"``: which activations a layer keeps for the backward),
    ``scan_layers`` (``lax.scan`` over runs of identical layers: compile time flat in depth;
    :func:`layer_runs` gives the runs), ``scan_breaks`` (layers that start a run of their own, so
    that a layer keeps its own name, e.g. MiLA stage 1's trainable last layer ``layers_27``),
    ``attn_impl`` for the attentions that run sequence-sharded (spatial, cross-view, full, HTFT)
    and ``local_attn_impl`` for those that never need communication (temporal, cross-attention
    to text and control tokens, the condition encoders); ``cross_attn_impl``, when set, takes the
    cross-attention to text and control tokens apart (:attr:`cross_impl`): on a TPU its long
    video queries against a few hundred keys gain from splash where the 8-frame temporal
    attention does not (docs/guides/plan.md's roofline). ``htft_layers``: layers after which STAGE's HTFT fuses past
    features (and whose outputs :meth:`DiT.__call__` returns with ``return_features``);
    ``htft_groups`` is its GroupNorm's group count, ``htft_dropout`` the rate of its
    ``Dropout(f)``.
    """

    layout: str = "factorized"
    depth: int = 2
    heads: int = 4
    head_dim: int = 16
    mlp_ratio: float = 4.0
    in_channels: int = 16
    out_channels: int | None = None
    patch: tuple[int, int, int] = (1, 2, 2)
    block: str = "stdit3"
    temporal: str = "on"
    multiview: str = "joint"
    neighbor_offsets: tuple[int, ...] = (-1, 1)
    qk_norm: str = "rms"
    qkv_bias: bool = True
    norm_eps: float = 1e-6
    positions: str = "rope"
    rope_theta: float = 10000.0
    rope_base: tuple[int, int] | None = None
    spatial_interpolation_scale: float = 1.0
    temporal_interpolation_scale: float = 1.0
    time_embed_dim: int | None = None
    time_freq_dim: int = 256
    flip_sin_to_cos: bool = True
    freq_shift: float = 0.0
    timestep_scale: float = 1000.0
    text_dim: int = 4096
    text_len: int = 300
    ofs_embed_dim: int | None = None
    controls: Controls = field(default_factory=Controls)
    box_range: float | None = 51.2
    box_freqs: int = 8
    prediction: str = "velocity"
    prediction_min_sigma: float = 0.05
    sigma_data: float = 0.0
    final_conv: int = 0
    out_patches: str = "disjoint"
    vae_temporal: int = 4
    vae_spatial: int = 8
    dtype: str = "float32"
    remat: str = "none"
    scan_layers: bool = False
    scan_breaks: tuple[int, ...] = ()
    attn_impl: str = "auto"
    local_attn_impl: str = "xla"
    cross_attn_impl: str | None = None
    htft_layers: tuple[int, ...] = ()
    htft_groups: int = 8
    htft_dropout: float = 0.0

    @property
    def width(self) -> int:
        return self.heads * self.head_dim

    @property
    def out_dim(self) -> int:
        return self.in_channels if self.out_channels is None else self.out_channels

    @property
    def t_dim(self) -> int:
        return self.width if self.time_embed_dim is None else self.time_embed_dim

    @property
    def cross_impl(self) -> str:
        """The kernel of the cross-attention to text and control tokens."""
        return self.local_attn_impl if self.cross_attn_impl is None else self.cross_attn_impl

    @property
    def compute_dtype(self):
        return jnp.dtype(self.dtype)

    @property
    def patch_dim(self) -> int:
        pt, ph, pw = self.patch
        return pt * ph * pw * self.in_channels

    def replace(self, **changes) -> DiTConfig:
        """A copy with ``changes``; ``controls=dict(...)`` updates fields of the controls."""
        if isinstance(changes.get("controls"), dict):
            changes["controls"] = dataclasses.replace(self.controls, **changes["controls"])
        return check_config(dataclasses.replace(self, **changes))


def check_config(cfg: DiTConfig) -> DiTConfig:
    """Validate ``cfg``; raises ``ValueError`` naming the field, the expected and the actual value."""
    _check_choices(cfg)
    _check_sizes(cfg)
    _check_width(cfg)
    _check_conditioning(cfg)
    _check_layer_indices(cfg)
    return cfg


def _check_choices(cfg: DiTConfig) -> None:
    """The named options (layout, block, dtype, ...) and the prediction target."""
    check_choice("layout", cfg.layout, LAYOUTS)
    check_choice("block", cfg.block, BLOCKS)
    check_choice("temporal", cfg.temporal, TEMPORAL)
    check_choice("out_patches", cfg.out_patches, OUT_PATCHES)
    if cfg.temporal != "on" and (cfg.layout, cfg.block) != ("factorized", "stdit3"):
        raise ValueError(
            f"temporal: expected 'on' for layout {cfg.layout!r} with block {cfg.block!r} (only the "
            f"factorized stdit3 layer has separate temporal blocks to drop or grow), got {cfg.temporal!r}"
        )
    check_choice("multiview", cfg.multiview, MULTIVIEW)
    check_choice("qk_norm", cfg.qk_norm, QK_NORMS)
    check_choice("positions", cfg.positions, POSITIONS)
    check_choice("remat", cfg.remat, REMAT)
    check_choice("dtype", cfg.dtype, DTYPES)
    check_choice("attn_impl", cfg.attn_impl, IMPLS)
    check_choice("local_attn_impl", cfg.local_attn_impl, LOCAL_IMPLS)
    if cfg.cross_attn_impl is not None:
        check_choice("cross_attn_impl", cfg.cross_attn_impl, LOCAL_IMPLS)
    check_choice("controls.text", cfg.controls.text, TEXT_KINDS)
    check_choice("controls.cond_frames", cfg.controls.cond_frames, COND_FRAMES)
    check_choice("prediction", cfg.prediction, PREDICTIONS)
    if not 0.0 < cfg.prediction_min_sigma <= 1.0:
        raise ValueError(f"prediction_min_sigma: expected a level in (0, 1], got {cfg.prediction_min_sigma}")
    if not cfg.sigma_data >= 0.0:
        raise ValueError(f"sigma_data: expected a standard deviation >= 0 (0: off), got {cfg.sigma_data}")
    if cfg.sigma_data and cfg.prediction != "data":
        raise ValueError(
            f"sigma_data: expected 0 with prediction {cfg.prediction!r} (the skip preconditions a "
            f"data estimate), got {cfg.sigma_data}"
        )


def _check_sizes(cfg: DiTConfig) -> None:
    """The counts and sizes: positive integers, the box and layout ranges, the patch."""
    for name in (
        "depth",
        "heads",
        "head_dim",
        "in_channels",
        "text_dim",
        "text_len",
        "time_freq_dim",
        "vae_temporal",
        "vae_spatial",
        "htft_groups",
    ):
        check_positive_int(name, getattr(cfg, name))
    check_positive_int("final_conv", cfg.final_conv, minimum=0)
    if cfg.box_range is not None and (
        isinstance(cfg.box_range, bool)
        or not isinstance(cfg.box_range, (int, float))
        or not 0.0 < cfg.box_range < float("inf")
    ):
        raise ValueError(
            f"box_range: expected a positive number of metres (or None: raw metres), got {cfg.box_range!r}"
        )
    check_positive_int("box_freqs", cfg.box_freqs)
    for name in (
        "num_classes",
        "map_channels",
        "map_hidden",
        "fourier_freqs",
        "caption_vocab",
        "layout_hidden",
        "layout_samples",
    ):
        check_positive_int(f"controls.{name}", getattr(cfg.controls, name))
    bev = cfg.controls.layout_bev_range
    if (
        len(tuple(bev)) != 2
        or any(isinstance(r, bool) or not isinstance(r, (int, float)) for r in bev)
        or not all(0.0 < r < float("inf") for r in bev)
    ):
        raise ValueError(f"controls.layout_bev_range: expected two positive extents in metres (x, y), got {bev!r}")
    check_positive_int("controls.encoder_layers", cfg.controls.encoder_layers, minimum=0)
    check_positive_int("controls.caption_layers", cfg.controls.caption_layers, minimum=0)
    if len(cfg.patch) != 3:
        raise ValueError(f"patch: expected (pt, ph, pw), got {cfg.patch!r}")
    for p in cfg.patch:
        check_positive_int("patch", p)
    if cfg.out_patches == "overlap" and (cfg.patch[1] % 2 or cfg.patch[2] % 2):
        raise ValueError(
            f"out_patches: 'overlap' centres a 2 ph x 2 pw patch on each token, a margin of ph / 2 and "
            f"pw / 2 latents; expected an even patch height and width, got patch={tuple(cfg.patch)}"
        )


def _check_width(cfg: DiTConfig) -> None:
    """What the patch, the positions and the prediction need of the width and the head size."""
    if cfg.prediction == "velocity" and cfg.patch_dim > cfg.width:
        raise ValueError(
            f"prediction: a token of patch x in_channels = {cfg.patch_dim} numbers is wider than the "
            f"model (heads x head_dim = {cfg.width}), which cannot pass the token's noise through to "
            f"predict the velocity; expected prediction='data', a width of at least {cfg.patch_dim} "
            f"or a smaller patch, got prediction='velocity'"
        )
    if cfg.layout == "full" and cfg.positions == "rope" and cfg.head_dim % 8:
        raise ValueError(f"head_dim: 3D RoPE needs a multiple of 8, got {cfg.head_dim}")
    if cfg.layout == "factorized" and cfg.head_dim % 2:
        raise ValueError(f"head_dim: temporal RoPE needs an even head size, got {cfg.head_dim}")
    if cfg.layout == "full" and cfg.positions == "sincos" and cfg.width % 16:
        raise ValueError(f"heads * head_dim: 3D sin-cos positions need a width divisible by 16, got {cfg.width}")
    if cfg.layout == "factorized" and cfg.width % 4:
        raise ValueError(f"heads * head_dim: 2D sin-cos positions need a width divisible by 4, got {cfg.width}")


def _check_conditioning(cfg: DiTConfig) -> None:
    """The reference frame, the full layout's text and the map ControlNet against the rest."""
    check_choice("controls.reference_frame", cfg.controls.reference_frame, REFERENCE_FRAME)
    if cfg.controls.reference_frame and cfg.controls.cond_frames is None:
        raise ValueError(
            "controls.reference_frame: expected condition frames (controls.cond_frames 'replace' or "
            "'concat') to take the reference from, got cond_frames=None"
        )
    mode = cfg.controls.reference_frame
    if mode in ("residual", "warp") and cfg.prediction != "data":
        raise ValueError(
            f"controls.reference_frame: {mode!r} makes the output the change from the reference "
            f"latents, which needs prediction='data', got prediction={cfg.prediction!r}"
        )
    if mode == "warp" and not cfg.controls.warp:
        raise ValueError(
            "controls.reference_frame: 'warp' corrects the warped frames, which needs controls.warp=True, got False"
        )
    if mode in ("residual", "warp") and cfg.out_dim != cfg.in_channels:
        raise ValueError(
            f"out_channels: a residual to the given frame needs in_channels = {cfg.in_channels} outputs, "
            f"got {cfg.out_dim}"
        )
    if cfg.layout == "full" and cfg.controls.text is None:
        raise ValueError("controls.text: the full layout attends over [text; video] and needs a text control, got None")
    if cfg.controls.map and not 1 <= cfg.controls.map_blocks <= cfg.depth:
        raise ValueError(f"controls.map_blocks: expected 1 .. depth = {cfg.depth}, got {cfg.controls.map_blocks}")


def _check_layer_indices(cfg: DiTConfig) -> None:
    """The layers named by ``scan_breaks`` and ``htft_layers``, HTFT, ofs and cross-view settings."""
    for i in cfg.scan_breaks:
        if not 0 < i < cfg.depth:
            raise ValueError(f"scan_breaks: expected layer indices in (0, {cfg.depth}), got {i}")
    for i in cfg.htft_layers:
        if not 0 <= i < cfg.depth:
            raise ValueError(f"htft_layers: expected layer indices in [0, {cfg.depth}), got {i}")
    if len(set(cfg.htft_layers)) != len(cfg.htft_layers):
        raise ValueError(f"htft_layers: expected distinct layers, got {cfg.htft_layers}")
    if cfg.htft_layers and cfg.width % cfg.htft_groups:
        raise ValueError(f"htft_groups: expected a divisor of the width {cfg.width}, got {cfg.htft_groups}")
    if not 0.0 <= cfg.htft_dropout < 1.0:
        raise ValueError(f"htft_dropout: expected a rate in [0, 1), got {cfg.htft_dropout}")
    if cfg.ofs_embed_dim is not None and cfg.ofs_embed_dim != cfg.t_dim:
        raise ValueError(f"ofs_embed_dim: expected the time embedding size {cfg.t_dim}, got {cfg.ofs_embed_dim}")
    if cfg.multiview == "cross_view" and (not cfg.neighbor_offsets or 0 in cfg.neighbor_offsets):
        raise ValueError(f"neighbor_offsets: expected non-zero view offsets, got {cfg.neighbor_offsets}")


def layer_runs(cfg) -> list[tuple[int, int]]:
    """The base layers' runs ``[(start, end), ...]``: split at the map ControlNet's depth, after
    each HTFT layer and at ``scan_breaks``. Scanned (``scan_layers``), a run of more than one
    layer is one ``nn.scan`` whose parameters are ``layers_{start}_{end}``; a run of one layer,
    and every layer when unrolled, is ``layers_{i}``."""
    bounds = {0, cfg.depth} | {i + 1 for i in cfg.htft_layers} | set(cfg.scan_breaks)
    if cfg.controls.map:
        bounds.add(cfg.controls.map_blocks)
    edges = sorted(bounds)
    return list(zip(edges[:-1], edges[1:]))
