"""Training, synthetic data and ONNX export for the CCDN corner detector (never imported by the runtime)."""
