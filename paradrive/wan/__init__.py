"""Wan2.1's model pieces on a ParaDrive build: the VAE and the text encoder, VAE latents and the
text embedding as build outputs (``encode``), and the ReCamDriving model on diffusers' classes
(``recam``). Training on them, conversion for other trainers and generation are applications:
:mod:`paradrive.train`."""
