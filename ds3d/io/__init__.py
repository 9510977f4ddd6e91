"""Images and results in and out: decoding untrusted images, the sources frames come from, the
files a run writes, and the streamed runs over them (`ds3d predict`, Ray Data's `ds3d batch`)."""
