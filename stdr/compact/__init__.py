"""The compact model file (`model.stdrc`), in one package (docs/compactness.md):

* `codecs`: each tensor's codec (f16, q8, q4, vq:C, lowrank:R, cols), stateless;
* `file`: a model's state dict to and from the file's payload (format, version, spec), read by
  `stdr.model.load_model`;
* `finetune`: the vq codebooks and, quantization-aware, the quantized state the spec names
  (4DGS's grid), fine-tuned on the training frames;
* `pack`: the one writer, `write_compact` for a model and `pack` for a trained run.

`codecs` and `file` sit below the model (loading reads them); `finetune` and `pack` above it.
"""
