"""Pure PyTorch/NumPy model library: frame format, data generation, methods, training, evaluation.

Knows nothing of HTTP or Celery.
"""
