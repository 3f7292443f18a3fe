"""Celery workers that run dataset-generation, training, evaluation and benchmark jobs."""
