"""Images and results in and out: decoding untrusted images (images.py), the sources frames come
from (sources.py), one image's answer (prediction.py) and the files a run writes (writers.py).
Nothing here runs a pipeline: that is ds3d.runners."""
