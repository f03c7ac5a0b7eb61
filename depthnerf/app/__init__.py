"""``depthnerf app``: the local web page (Gradio) over :class:`~depthnerf.reconstruct.reconstructor.Reconstructor`."""
