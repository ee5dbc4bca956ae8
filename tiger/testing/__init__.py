"""Fixtures that tests, benchmarks and examples share, shipped so users can run them too.

Nothing in the rest of ``tiger`` imports this package; it sits above every other layer.

- :mod:`~tiger.testing.random_models`: randomly initialised CLIP, SAM, InstructPix2Pix and MVDream
  of the real architectures (``tiny`` for tests, ``full`` for benchmarks), saved in the public formats.
- :mod:`~tiger.testing.labelled_scene`: a synthetic labelled scene with known answers for retrieval
  and the language field.
- :mod:`~tiger.testing.ideal_denoiser`: score distillation with the ideal denoiser of known targets,
  the edit loop's known-answer guidance.
- :mod:`~tiger.testing.cuda_graphs`: capturing a function in a CUDA graph (warm-up on a side
  stream, then the capture), for the CUDA-graph tests of the ops.
"""

#: Nothing is re-exported here: import the modules (e.g. ``tiger.testing.random_models``) directly.
__all__: list[str] = []
