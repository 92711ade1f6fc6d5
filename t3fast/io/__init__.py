"""Files every layer reads and writes: dataclass configs as YAML/JSON with dotted overrides
(:mod:`t3fast.io.config`) and checkpoints written atomically and read safely
(:mod:`t3fast.io.checkpoint`). Inference loads checkpoints without the training stack."""
