"""``jaxdrive convert``: diffusers weights (safetensors) -> saved jaxdrive models."""

from __future__ import annotations


def _convert_vae(args, rest) -> int:
    from jaxdrive.convert.diffusers_vae import load_diffusers_vae
    from jaxdrive.models.pretrained import save_pretrained
    from jaxdrive.models.params import count_params

    vae, params = load_diffusers_vae(args.src)
    path = save_pretrained(args.dst, vae, params, overwrite=args.overwrite)
    print(f"wrote the VAE ({count_params(params):,} parameters, {len(vae.config.block_out_channels)} "
          f"blocks, {vae.config.latent_channels} latent channels) to {path}")
    return 0


def add_commands(sub) -> None:
    convert = sub.add_parser("convert", help="import diffusers weights (safetensors) as jaxdrive models")
    csub = convert.add_subparsers(dest="convert_command", metavar="CONVERT_COMMAND", required=True)
    vae = csub.add_parser("vae", help="diffusers AutoencoderKLCogVideoX directory -> jaxdrive model")
    vae.add_argument("src", help="diffusers directory (config.json + diffusion_pytorch_model.safetensors)")
    vae.add_argument("dst", help="directory to write (load with jaxdrive.models.pretrained.load_pretrained)")
    vae.add_argument("--overwrite", action="store_true")
    vae.set_defaults(run=_convert_vae)
