"""Whether the converted MediaPipe models are here (`telesplat track fetch-models`), for the
tests that track real images and skip with that reason otherwise."""

import pytest


def models_available() -> bool:
    try:
        from avatar_core.track.models import MODELS, model_path

        for name in MODELS:
            model_path(name)
    except Exception:  # noqa: BLE001 - any reason means: skip
        return False
    return True


needs_models = pytest.mark.skipif(not models_available(),
                                  reason="MediaPipe ONNX models not fetched "
                                         "(telesplat track fetch-models)")
