"""Monocular tracking: MediaPipe landmark models (converted to ONNX) and the fitting on top.

`models` fetches the MediaPipe wheel into a cache and converts its TFLite models with the
project's own converter (`convert`); nothing here installs or imports mediapipe.
"""
