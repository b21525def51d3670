"""Policies: the chapter-7 denoising network, its baselines, evaluation, and the plan service."""
