"""Checkpoints published on the Hugging Face Hub: ``hf://OWNER/REPO[/FILE][@REVISION]``.

A checkpoint is one ``.safetensors`` file that carries its inference spec (what training writes in
``RUN/checkpoints/*/model.safetensors``, or ``scripts/export_checkpoint.py``), so publishing one is uploading that
file to a model repository as ``model.safetensors``, with its card as ``README.md`` (``scripts/hub_folder.py`` lays
both out).
Wherever a checkpoint is accepted (``--checkpoint`` of ``eval`` / ``reconstruct`` / ``app``, ``--init-from``,
``Reconstructor.from_pretrained``), ``hf://OWNER/REPO`` names the repository's ``model.safetensors``;
``hf://OWNER/REPO/sub/dir/cars.safetensors`` another file in it, and a trailing ``@REVISION`` a branch, tag or
commit (default ``main``).

``huggingface_hub`` downloads the file into its cache (``HF_HUB_CACHE``, by default ``~/.cache/huggingface/hub``)
and checks it against the Hub on later calls; when the Hub cannot be reached (:func:`~depthnerf.hub_access.
hub_reachable`; ``HF_HUB_OFFLINE=1`` says so too) only the cache is read, at once.
Only ``.safetensors`` files are accepted: nothing is unpickled, and the file is then loaded exactly as a local one
(strictly, its spec and weights checked).
"""

from __future__ import annotations

from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.hub_access import hub_reachable

HUB_PREFIX = "hf://"
"""The prefix that marks a checkpoint reference as a Hugging Face Hub file."""
HUB_DEFAULT_FILE = "model.safetensors"
"""The file of a repository that ``hf://OWNER/REPO`` names."""


def is_hub_reference(checkpoint: object) -> bool:
    """True for a string that starts with :data:`HUB_PREFIX`."""
    return isinstance(checkpoint, str) and checkpoint.startswith(HUB_PREFIX)


def parse_hub_reference(reference: str) -> tuple[str, str, str | None]:
    """``hf://OWNER/REPO[/FILE][@REVISION]`` -> ``(repo_id, filename, revision or None)``; a malformed reference
    (no owner or repository, an empty revision, a ``.`` or ``..`` segment, a file that is not ``.safetensors``)
    is a one-line error."""
    body = reference[len(HUB_PREFIX):]
    revision = None
    if "@" in body:
        body, revision = body.rsplit("@", 1)
        if not revision:
            raise DepthnerfError(f"{reference}: empty revision after '@' (write hf://OWNER/REPO@BRANCH_TAG_OR_COMMIT)")
    parts = [p for p in body.split("/") if p]
    if len(parts) < 2:
        raise DepthnerfError(f"{reference}: a Hub checkpoint is hf://OWNER/REPO[/FILE][@REVISION]")
    if any(p in (".", "..") for p in parts):
        raise DepthnerfError(f"{reference}: '.' and '..' are not allowed in a Hub path "
                             "(hf://OWNER/REPO[/FILE][@REVISION])")
    filename = "/".join(parts[2:]) or HUB_DEFAULT_FILE
    if not filename.endswith(".safetensors"):
        raise DepthnerfError(f"{reference}: {filename} is not a .safetensors file; only safetensors checkpoints "
                             f"load (nothing is unpickled)")
    return f"{parts[0]}/{parts[1]}", filename, revision


def fetch_hub_checkpoint(reference: str) -> Path:
    """The local path of the Hub file ``reference`` names, downloaded into the Hugging Face cache if it is not
    there yet (see the module docstring). Every failure is one line naming the reference."""
    repo_id, filename, revision = parse_hub_reference(reference)
    try:
        from huggingface_hub import hf_hub_download
        from huggingface_hub.errors import (
            EntryNotFoundError,
            HFValidationError,
            LocalEntryNotFoundError,
            RepositoryNotFoundError,
            RevisionNotFoundError,
        )
    except ImportError as err:
        raise DepthnerfError(f"{reference}: loading from the Hub needs huggingface_hub (pip install "
                             f"huggingface_hub): {err}") from None
    try:
        return Path(hf_hub_download(repo_id, filename, revision=revision, local_files_only=not hub_reachable()))
    except LocalEntryNotFoundError:
        raise DepthnerfError(f"{reference}: not in the local Hugging Face cache, and the Hub could not be reached "
                             f"(no network, or HF_HUB_OFFLINE is set)") from None
    except RevisionNotFoundError:
        raise DepthnerfError(f"{reference}: {repo_id} has no revision {revision}") from None
    except EntryNotFoundError:
        raise DepthnerfError(f"{reference}: {repo_id} has no file {filename}"
                             f"{'' if revision is None else f' at {revision}'}") from None
    except RepositoryNotFoundError:
        raise DepthnerfError(f"{reference}: no model repository {repo_id} on the Hub (a private or gated one "
                             f"needs `hf auth login`)") from None
    except HFValidationError as err:
        raise DepthnerfError(f"{reference}: {str(err).splitlines()[0]}") from None
    except Exception as err:  # noqa: BLE001 - network and file-system failures (httpx's are not OSErrors)
        raise DepthnerfError(f"{reference}: download failed: {str(err).splitlines()[0] if str(err) else err!r}") \
            from None
