"""admc.pipeline.stages: what each admc-pipe command does (render, dataset, train, evaluate, denoise, export)
as a function of a Config."""
