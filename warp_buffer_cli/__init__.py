"""The ``warp-buffer`` command line: ``info``, ``demo`` (the main job) and ``bench``."""
