"""The dataset's files: one home for the formats that `synth` writes and `training`, `hgca eval` and the
benchmarks read, so that a reader never imports the simulator (and its Embree) to open a sample.

- `samples`: the full synthetic samples (CONTRACTS.md): split names and seed spans, the format version, the keys,
  writing and reading one file, a split's files.
- `packed`: the packed coarse samples (`hgca synth --pack`): the coarse stage's 20 cm cells as bit grids.
"""
