"""What drives a Pipeline over many images: predictions streamed from any source (predict.py),
a batch split among worker processes (workers.py), Ray Data's actor pool (ray_data.py)."""
