"""A generic, cached, staged DAG engine. It knows nothing of Gaussians or images."""
