"""What every part of ds3d leans on and none is about pose: where files are, progress bars,
stage timings, CPU threads, the process's memory."""
