"""One photo in, 3D out: photo reading and framing, the :class:`Reconstructor`, orbits, exports and the demo."""
