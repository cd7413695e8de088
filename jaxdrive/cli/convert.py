"""``jaxdrive convert``: diffusers weights (safetensors) -> saved jaxdrive models; the FID Inception's
``.pth`` -> safetensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _convert_vae(args, rest) -> int:
    from jaxdrive.convert.diffusers_vae import load_diffusers_vae
    from jaxdrive.models.params import count_params
    from jaxdrive.models.pretrained import save_pretrained

    vae, params = load_diffusers_vae(args.src)
    path = save_pretrained(args.dst, vae, params, overwrite=args.overwrite)
    print(
        f"wrote the VAE ({count_params(params):,} parameters, {len(vae.config.block_out_channels)} "
        f"blocks, {vae.config.latent_channels} latent channels) to {path}"
    )
    return 0


def _convert_eval_network(args, rest) -> int:
    """An evaluation network's torch state dict -> safetensors, checked to be that network's."""
    from safetensors.numpy import save_file

    from jaxdrive.eval import i3d, inception
    from jaxdrive.eval.weights import read_state_dict

    check = {"inception": inception.params_from_state_dict, "i3d": i3d.params_from_state_dict}[args.network]
    state = read_state_dict(args.src, option="--from")
    check(state, source=f"--from {args.src}")  # that network's tensors, or refused
    out = Path(args.dst)
    if out.suffix != ".safetensors":
        raise ValueError(f"--out: expected a path ending in .safetensors, got {str(out)!r}")
    if out.exists() and not args.overwrite:
        raise ValueError(f"--out: {out} exists (pass --overwrite to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    save_file({k: np.ascontiguousarray(v) for k, v in state.items()}, str(tmp))
    tmp.replace(out)  # atomic: a crash leaves no half-written file
    print(f"wrote the {args.network} network's {len(state)} tensors to {out}")
    return 0


def add_commands(sub) -> None:
    convert = sub.add_parser("convert", help="import diffusers weights (safetensors) as jaxdrive models")
    csub = convert.add_subparsers(dest="convert_command", metavar="CONVERT_COMMAND", required=True)
    vae = csub.add_parser("vae", help="diffusers AutoencoderKLCogVideoX directory -> jaxdrive model")
    vae.add_argument("src", help="diffusers directory (config.json + diffusion_pytorch_model.safetensors)")
    vae.add_argument("dst", help="directory to write (load with jaxdrive.models.pretrained.load_pretrained)")
    vae.add_argument("--overwrite", action="store_true")
    vae.set_defaults(run=_convert_vae)
    for network, src, what in (
        ("inception", "pt_inception-2015-12-05-6726825d.pth", "pytorch-fid's FID Inception"),
        ("i3d", "i3d_pretrained_400.pt", "cd-fvd's I3D of FVD"),
    ):
        cmd = csub.add_parser(network, help=f"{what} (.pth state dict) -> safetensors (no torch needed to evaluate)")
        cmd.add_argument("--from", dest="src", required=True, help=src)
        cmd.add_argument("--out", dest="dst", required=True, help="FILE.safetensors to write")
        cmd.add_argument("--overwrite", action="store_true")
        cmd.set_defaults(run=_convert_eval_network, network=network)
