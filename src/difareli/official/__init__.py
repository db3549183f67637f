"""The authors' released code's artefacts: their checkpoints (weights) and preprocessed layouts."""
