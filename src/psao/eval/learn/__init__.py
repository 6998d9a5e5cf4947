"""Training of the learned AO baselines (`psao train nnao|mlp`): small numpy networks, seeded."""
