"""Client renderer (moderngl): G-buffer, PSAO reconstruction, SSAO baseline, composite.

Heavy imports (moderngl) happen when a renderer is created, not at package import.
"""
