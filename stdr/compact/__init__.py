"""Packing a trained model into its compact file (`model.stdrc`, docs/compactness.md), above the
model and the evaluation:

* `pack`: the one writer, `write_compact` for a model and `pack` for a trained run (it measures
  what it wrote);
* `finetune`: the vq codebooks and, quantization-aware, the quantized state the spec names
  (4DGS's grid), fine-tuned on the training frames.

The file's format (codecs, entropy coding, the payload, the methods' optional hooks) is
`stdr.compression`, below the model, which reads compact files through it.
"""
