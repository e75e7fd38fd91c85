"""Wan2.1 on a ParaDrive build: VAE latents and the text embedding as build outputs, the
ReCamDriving model on diffusers' classes, and hand-offs to the trainers users run."""
