"""Training of the learned priors, kept apart from inference (as diffusers keeps examples/
apart from pipelines/): core/priors runs a model, core/training fits one."""
