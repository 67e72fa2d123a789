"""admc.model.training: adversarial training of the two branches, from patch batches to shipped weights."""
