"""Imported once by the fork server of the Embree worker pools (embree.worker_context): the tracer's module
and its Warp ray kernels are loaded there, so every worker forked from it starts with them. Nothing here
builds an Embree scene: the fork server must never start Embree's threads."""
from psao.server.tracer.embree import load_ray_kernels

load_ray_kernels()
