"""Benchmarks: warp-buffer's transport paths side by side with the peers a Python user would pick.

Entry point: ``benchmarks.run`` (wired as ``warp-buffer bench``).
"""
