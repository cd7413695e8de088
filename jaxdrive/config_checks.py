"""The range and pairing checks of a :class:`jaxdrive.config.Config`'s sections, run before
anything compiles (:func:`check_sections`; the model's own config checks itself in
:func:`jaxdrive.models.dit.config.check_config`, called from here). Each names the option, the
expected and the actual value."""

from __future__ import annotations

from jaxdrive import validate
from jaxdrive.flow.patterns import check_patterns
from jaxdrive.models.dit.config import check_config


def check_self_rollout(config) -> None:
    """What training a rollout's second window (``flow.self_rollout_rate``,
    :mod:`jaxdrive.train.self_rollout`) needs: exactly ``flow.cond_frames`` given frames at the
    start of every window, one clip length, pixels in the batch, and no other kind of step."""
    f, d = config.flow, config.data
    validate.check_range("flow.self_rollout_rate", f.self_rollout_rate, 0.0, 1.0)
    validate.check_positive_int("flow.self_rollout_steps", f.self_rollout_steps)
    needs = (
        ("flow.cond_frames", f.cond_frames >= 1, "at least 1 given frame", f.cond_frames),
        ("flow.cond_frames_random", not f.cond_frames_random, "false (every window has its given frames)", True),
        ("flow.patterns", tuple(f.patterns) == ("prefix",), "('prefix',)", tuple(f.patterns)),
        ("flow.jdc_anchor_rate", f.jdc_anchor_rate == 0, "0", f.jdc_anchor_rate),
        ("data.buckets", not d.buckets, "() (one clip length)", d.buckets),
        ("data.stride", d.stride == 1, "1", d.stride),
        ("data.rate_strides", not d.rate_strides, "()", d.rate_strides),
        ("latents.precomputed", not config.latents.precomputed, "false (clips of 2F - k frames)", True),
        ("stream.enabled", not config.stream.enabled, "false (STAGE's has its own: stream.self_rollout)", True),
        ("flow.distill_teacher", not f.distill_teacher, "''", f.distill_teacher),
        ("data.frames", d.frames > f.cond_frames, f"more than flow.cond_frames = {f.cond_frames}", d.frames),
    )
    for name, ok, expected, got in needs:
        if not ok:
            raise ValueError(f"{name}: expected {expected} with flow.self_rollout_rate > 0, got {got!r}")


def check_warp_path(config) -> None:
    """``flow.warp_path_rate``: a share in [0, 1]; above 0 only for a model that reads the warp
    (there is no warp to noise otherwise) and on steps whose noisy inputs are the plain path's
    (JDC's anchors and the distillation's coarse frames make their own)."""
    f = config.flow
    validate.check_range("flow.warp_path_rate", f.warp_path_rate, 0.0, 1.0)
    if not f.warp_path_rate:
        return
    needs = (
        ("model.controls.warp", config.model.controls.warp, "true (the warp the inputs are noised from)", False),
        ("flow.jdc_anchor_rate", f.jdc_anchor_rate == 0, "0", f.jdc_anchor_rate),
        ("flow.distill_teacher", not f.distill_teacher, "''", f.distill_teacher),
    )
    for name, ok, expected, got in needs:
        if not ok:
            raise ValueError(f"{name}: expected {expected} with flow.warp_path_rate > 0, got {got!r}")


def check_warp_start(level, model=None) -> None:
    """``sample.warp_start``: a noise level in (0, 1]; below 1 only for a model that
    reads the warp (``model.controls.warp``, a :class:`jaxdrive.models.dit.config.DiTConfig`),
    whose windows have a warp to start from."""
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0.0 < level <= 1.0:
        raise ValueError(f"sample.warp_start: expected a noise level in (0, 1], got {level!r}")
    if level < 1.0 and model is not None and not model.controls.warp:
        raise ValueError(
            f"sample.warp_start: expected 1 (pure noise) for a model without the warp "
            f"(model.controls.warp false), got {level!r}"
        )


def check_sections(config) -> None:
    """Range checks of the sections :mod:`jaxdrive.config` defines (the model's config checks itself)."""
    d, o, t, f = config.data, config.optim, config.train, config.flow
    for name, value in (
        ("data.frames", d.frames),
        ("data.height", d.height),
        ("data.width", d.width),
        ("data.views", d.views),
        ("data.stride", d.stride),
        ("data.batch_size", d.batch_size),
        ("optim.grad_accum", o.grad_accum),
        ("train.steps", t.steps),
        ("train.log_every", t.log_every),
        ("train.max_bad_steps", t.max_bad_steps),
    ):
        validate.check_positive_int(name, value)
    validate.check_range("data.drop_prob", d.drop_prob, 0.0, 1.0)
    validate.check_range("optim.lr", o.lr, 0.0, float("inf"), lo_open=True)
    validate.check_range("optim.ema_decay", o.ema_decay, 0.0, 1.0, hi_open=True)
    validate.check_choice("optim.schedule", o.schedule, ("cosine", "linear", "constant"))
    validate.check_choice("train.on_save_error", t.on_save_error, ("continue", "stop"))
    validate.check_choice("flow.sigma_sampling", f.sigma_sampling, ("logit_normal", "uniform"))
    validate.check_range("flow.jdc_anchor_rate", f.jdc_anchor_rate, 0.0, 1.0)
    validate.check_range("flow.jdc_alpha1", f.jdc_alpha1, 0.0, 1.0, hi_open=True)
    check_patterns(f.patterns, f.pattern_rates, f.anchor_every, prefix="flow.")
    validate.check_choice("train.compute_dtype", t.compute_dtype, ("float32", "bfloat16"))
    validate.check_choice("latents.source", config.latents.source, ("vae", "space_to_depth"))
    validate.check_range("optim.min_lr_ratio", o.min_lr_ratio, 0.0, 1.0)
    validate.check_range("flow.structure_cutoff", f.structure_cutoff, 0.0, 1.0)
    validate.check_range("flow.foreground_k", f.foreground_k, 0.0, float("inf"))
    validate.check_range("flow.foreground_c", f.foreground_c, 0.0, float("inf"))
    if f.distill_teacher:
        validate.check_positive_int("flow.distill_segment_len", f.distill_segment_len, minimum=2)
        validate.check_choice("flow.distill_boundary", f.distill_boundary, ("mean", "start", "end"))
        validate.check_range("flow.distill_weight", f.distill_weight, 0.0, float("inf"))
        # eq. 7-8 put one level on the whole dense clip: per-frame schedules have no dense reading
        if f.tpd:
            raise ValueError(
                "flow.tpd: expected false with flow.distill_teacher (LongDWM's distillation puts "
                "one noise level on the whole dense clip), got true"
            )
        if f.jdc_anchor_rate > 0:
            raise ValueError(
                f"flow.jdc_anchor_rate: expected 0 with flow.distill_teacher (one noise level on "
                f"the whole dense clip), got {f.jdc_anchor_rate}"
            )
        if (d.frames - 1) % (f.distill_segment_len - 1):
            raise ValueError(
                f"data.frames: expected n * (flow.distill_segment_len - 1) + 1 dense frames for "
                f"distillation (segment_len = {f.distill_segment_len}), got {d.frames}"
            )
    if f.cond_frames < 0:
        raise ValueError(f"flow.cond_frames: expected >= 0, got {f.cond_frames}")
    for name, level in (("flow.given_noise_max", f.given_noise_max), ("flow.given_noise_sample", f.given_noise_sample)):
        if not (isinstance(level, (int, float)) and 0.0 <= level < 1.0):
            raise ValueError(f"{name}: expected a noise level in [0, 1), got {level!r}")
    if f.given_noise_sample > f.given_noise_max:
        raise ValueError(
            f"flow.given_noise_sample: expected a level the model trained with, at most flow.given_noise_max = "
            f"{f.given_noise_max}, got {f.given_noise_sample}"
        )
    if f.self_rollout_rate:
        check_self_rollout(config)
    check_warp_path(config)
    if f.given_noise_max > 0 and config.model.controls.cond_frames != "replace":
        raise ValueError(
            f"flow.given_noise_max: the given frames' noise level reaches the model with "
            f"model.controls.cond_frames 'replace', got {config.model.controls.cond_frames!r}"
        )
    validate.check_positive_int("data.rate_head", d.rate_head, minimum=0)
    if d.rate_head > d.frames:
        raise ValueError(f"data.rate_head: expected at most data.frames = {d.frames} frames, got {d.rate_head}")
    for s in d.rate_strides:
        if isinstance(s, bool) or not isinstance(s, int) or s < 1:
            raise ValueError(f"data.rate_strides: expected positive integers, got {d.rate_strides!r}")
    if d.rate_strides and config.latents.precomputed:
        raise ValueError(
            f"data.rate_strides: expected () with latents.precomputed (stored latent windows have "
            f"uniform frames), got {d.rate_strides!r}"
        )
    if d.rate_strides and f.distill_teacher:
        raise ValueError(
            f"data.rate_strides: expected () with flow.distill_teacher (distillation cuts a uniform "
            f"dense clip into segments), got {d.rate_strides!r}"
        )
    parting = validate.check_probability("data.route_parting", d.route_parting)
    mix = {}
    if d.routes:
        from jaxdrive.data.route_mix import parse_route_mix

        mix = parse_route_mix(d.routes)
        if config.latents.precomputed:
            raise ValueError(
                f"data.routes: expected () with latents.precomputed (latent windows are cut from the "
                f"recorded clips), got {d.routes!r}"
            )
    if parting and set(mix) <= {"recorded"}:
        raise ValueError(
            f"data.route_parting: expected 0 without a counterfactual route in data.routes (nothing parts), "
            f"got {parting} with data.routes={d.routes!r}"
        )
    if d.buckets:
        from jaxdrive.data.buckets import parse_bucket_specs

        parse_bucket_specs(d.buckets)
        for name, value, ok in (
            ("latents.precomputed", config.latents.precomputed, False),
            ("flow.distill_teacher", f.distill_teacher, ""),
            ("optim.grad_accum", o.grad_accum, 1),
        ):
            if value != ok:  # stored windows have one shape; a step's micro-batches must share a bucket
                raise ValueError(f"{name}: expected {ok!r} with data.buckets, got {value!r}")
    if hasattr(config, "sample"):
        validate.check_range("sample.cfg", config.sample.cfg, 0.0, float("inf"), hi_open=True)
        check_warp_start(config.sample.warp_start, getattr(config, "model", None))
    if hasattr(config, "model"):
        check_config(config.model)
