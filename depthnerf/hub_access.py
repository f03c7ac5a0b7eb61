"""Whether the Hugging Face Hub can be reached, asked once before a download that would otherwise retry.

``huggingface_hub`` retries an unreachable host for about 25 seconds, logging each retry, before it falls back to
its cache; offline (this project's CI, air-gapped clusters) every load of a hub id would pay that. Loaders that
accept hub ids (the Depth Anything V2 backend, ``hf://`` checkpoints) ask :func:`hub_reachable` first and read only
the local cache when it says no.
"""

from __future__ import annotations


def hub_reachable(timeout: float = 5.0) -> bool:
    """False when ``HF_HUB_OFFLINE`` is set or the hub's host does not answer a TCP connect within ``timeout``
    seconds (saves the minutes of retries ``from_pretrained`` spends offline)."""
    import socket
    from urllib.parse import urlparse

    from huggingface_hub import constants

    if constants.HF_HUB_OFFLINE:
        return False
    url = urlparse(constants.ENDPOINT)
    try:
        socket.create_connection((url.hostname, url.port or (443 if url.scheme == "https" else 80)),
                                 timeout=timeout).close()
    except OSError:
        return False
    return True
