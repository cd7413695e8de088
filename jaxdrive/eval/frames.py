"""Frame fidelity of a generated clip against the recorded clip it continues: PSNR and SSIM per
frame, beside the repeat-the-last-frame and noise baselines. The metrics live where generation
scores its own samples, :mod:`jaxdrive.generate.quality`; re-exported here.
"""

from jaxdrive.generate.quality import FrameScores, clip_quality, noise_like, psnr, ssim  # noqa: F401
