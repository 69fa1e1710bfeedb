"""The compact model file's format (`model.stdrc`, docs/compactness.md), below the model:

* `codecs`: each tensor's codec (f16, q8, q4, vq:C, lowrank:R, cols), stateless;
* `entropy`: lossless Zstandard coding of the encoded streams;
* `file`: a model's state dict to and from the file's payload (format, version, spec), read by
  `stdr.model.load_model`;
* `hooks`: the optional protocol through which a baseline's deformation or a plug-in says how the
  file stores its tables (`CompactColumns`, `CompactPlugin`).

Writing a trained run's file (`stdr.compact.pack`) and fine-tuning its codebooks
(`stdr.compact.finetune`) are a tool above the model, in `stdr.compact`.
"""
