"""Fine-tuning the diffusion prior (UNet + depth ControlNet) on lightfield-balls data:
data (the dataset reader), train (the loop, `lightfield train-prior`), checkpoint
(resumable training state without pickle). See docs/diffusion-prior.md."""
