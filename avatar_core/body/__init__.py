"""Body models: loaders, linear blend skinning, the upper-body cut, FLAME/MANO fusion."""
