"""Fine-tuning the 3D causal VAE: reconstruction + KL loss and a jitted train step.

The loss of a latent-diffusion autoencoder (Rombach et al. 2022, "High-Resolution Image Synthesis
with Latent Diffusion Models", sec. 3 and appendix G), as used to train CogVideoX's VAE:

    L = rec(D(z), x) + kl_weight * KL(q(z | x) || N(0, I)) + perceptual_weight * P(D(z), x),
    z = mu + exp(logvar / 2) * eps,

with ``rec`` the mean absolute (``"l1"``) or squared (``"l2"``) error over pixels and
``KL = 1/2 sum(mu^2 + exp(logvar) - 1 - logvar)`` summed over each clip's latent elements and
averaged over clips (so ``kl_weight`` is per clip, LDM's convention; default 1e-6). ``P`` is an
optional perceptual loss the user brings (e.g. LPIPS in JAX): ``perceptual(pred, target) ->
scalar`` over frames ``[N, H, W, 3]`` in [-1, 1]. The adversarial term of the original recipe is
left to the user; a discriminator loss can be folded into ``perceptual``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import optax

from jaxdrive import validate
from jaxdrive.models.vae.model import CausalVAE


@dataclasses.dataclass(frozen=True)
class VAELossConfig:
    recon: str = "l1"  # "l1" or "l2"
    kl_weight: float = 1e-6
    perceptual_weight: float = 0.0
    mode: str | None = None  # the VAE's pass while training; None = its config's mode

    def __post_init__(self):
        validate.check_choice("recon", self.recon, ("l1", "l2"))
        validate.check_range("kl_weight", self.kl_weight, 0.0, float("inf"))
        validate.check_range("perceptual_weight", self.perceptual_weight, 0.0, float("inf"))


def kl_to_standard_normal(mean, logvar):
    """``1/2 sum(mu^2 + exp(logvar) - 1 - logvar)`` per clip (all axes but the first), ``[N]``."""
    terms = jnp.square(mean) + jnp.exp(logvar) - 1.0 - logvar
    return 0.5 * jnp.sum(terms.reshape(terms.shape[0], -1), axis=1)


def vae_loss(
    vae: CausalVAE, params, video, key, config: VAELossConfig = VAELossConfig(), perceptual: Callable | None = None
):
    """``(loss, metrics)`` of the VAE on ``video [B, (V,) F, H, W, 3]`` in [-1, 1] (see the module
    docstring); ``key`` draws the posterior sample."""
    if config.perceptual_weight > 0 and perceptual is None:
        raise ValueError("perceptual: expected a callable when perceptual_weight > 0, got None")
    mean, logvar = vae.posterior(params, video, mode=config.mode)
    z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape, mean.dtype)
    recon = vae.decode(params, z, mode=config.mode)
    err = recon - video
    rec = jnp.mean(jnp.abs(err)) if config.recon == "l1" else jnp.mean(jnp.square(err))
    kl = jnp.mean(kl_to_standard_normal(mean.reshape(-1, *mean.shape[-4:]), logvar.reshape(-1, *logvar.shape[-4:])))
    loss = rec + config.kl_weight * kl
    metrics = {"recon": rec, "kl": kl}
    if perceptual is not None and config.perceptual_weight > 0:
        frames = lambda x: x.reshape(-1, *x.shape[-3:])
        metrics["perceptual"] = perceptual(frames(recon), frames(video))
        loss = loss + config.perceptual_weight * metrics["perceptual"]
    metrics["loss"] = loss
    return loss, metrics


def make_vae_train_step(
    vae: CausalVAE,
    optimizer: optax.GradientTransformation,
    config: VAELossConfig = VAELossConfig(),
    perceptual: Callable | None = None,
):
    """A jitted ``step(params, opt_state, video, key) -> (params, opt_state, metrics)``; params and
    optimizer state are donated. Use ``optimizer.init(params)`` for the first ``opt_state``."""

    def step(params, opt_state, video, key):
        grad_fn = jax.value_and_grad(lambda p: vae_loss(vae, p, video, key, config, perceptual), has_aux=True)
        (_, metrics), grads = grad_fn(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        metrics["grad_norm"] = optax.tree_utils.tree_norm(grads)
        return optax.apply_updates(params, updates), opt_state, metrics

    return jax.jit(step, donate_argnums=(0, 1))
