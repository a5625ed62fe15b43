"""The motion library: keyframed SMPL-X parameter tracks (`keyframes`), the named clips the
server offers at /v1/motions (`library`) and a body model's rig that turns a clip into the
parameters of that model (`rig`)."""
