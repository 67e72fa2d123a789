"""admc.model.nets: the networks (generator backbones, encoder, critic), their losses and the [model] settings."""
