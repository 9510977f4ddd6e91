"""Pictures of results: fast OpenCV overlays of every frame, and the paper-style figure."""
