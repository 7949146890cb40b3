"""Grounding DINO through one ONNX graph, with the caption tokenised on the host.

The caption is lower-cased, stripped and ends with " ."; it is tokenised offline with the
``tokenizers`` package's BertWordPieceTokenizer on the user's ``vocab.txt``. Position ids
restart at 0 after every special token ([CLS], [SEP], '.', '?') and the phrase mask lets
each token attend only within its '.'-separated phrase, as upstream builds them.
Scoring is upstream's: a query is kept when its best token probability exceeds the box
threshold; its phrase is the tokens above the text threshold (which never removes a box).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Tuple

import numpy as np

from cobgs.errors import InputError, ModelError

from cobgs.masks.images import to_model_input
from cobgs.masks.manifest import GdinoManifest, keep_aspect_size
from cobgs.masks.session import GraphSession, SessionOptions


@dataclass(frozen=True)
class TextInputs:
    """Host-built text tensors for a caption of L tokens."""

    input_ids: np.ndarray  # int64 [1, L]
    attention_mask: np.ndarray  # bool [1, L]
    position_ids: np.ndarray  # int64 [1, L]
    token_type_ids: np.ndarray  # int64 [1, L]
    text_token_mask: np.ndarray  # bool [1, L, L]
    tokens: Tuple[str, ...]


@dataclass(frozen=True)
class Detection:
    """One kept query.

    Attributes:
        box_xyxy: (x0, y0, x1, y1) in the frame's own pixels.
        confidence: max token probability of the query.
        phrase: the caption words whose probability exceeds the text threshold.
    """

    box_xyxy: Tuple[float, float, float, float]
    confidence: float
    phrase: str


def normalise_caption(caption: str) -> str:
    text = caption.lower().strip()
    if not text:
        raise InputError("text prompt is empty")
    return text if text.endswith(".") else text + " ."


def phrase_masks(ids: np.ndarray, special_ids) -> Tuple[np.ndarray, np.ndarray]:
    """Block-diagonal phrase self-attention mask and restarting position ids.

    Args:
        ids: int64 [L] token ids of one caption (with [CLS] first and [SEP] last).

    Returns:
        (mask bool [L, L], position_ids int64 [L]).
    """
    n = ids.shape[0]
    mask = np.eye(n, dtype=bool)
    pos = np.zeros(n, np.int64)
    prev = 0
    for col in np.flatnonzero(np.isin(ids, list(special_ids))):
        if col == 0 or col == n - 1:
            pos[col] = 0  # [CLS] and [SEP] attend to themselves only
        else:
            mask[prev + 1:col + 1, prev + 1:col + 1] = True
            pos[prev + 1:col + 1] = np.arange(col - prev)
        prev = col
    return mask, pos


class Tokenizer:
    """BERT word-piece tokeniser over the user's ``vocab.txt`` (no network)."""

    def __init__(self, vocab_path, max_len: int, special_ids):
        from tokenizers import BertWordPieceTokenizer

        try:
            self._tok = BertWordPieceTokenizer(str(vocab_path), lowercase=True)
        except Exception as exc:  # tokenizers raises its own exception type
            raise ModelError(f"cannot read the BERT vocabulary: {exc}", vocab_path) from exc
        self.max_len = int(max_len)
        self.special_ids = tuple(int(i) for i in special_ids)

    def __call__(self, caption: str) -> TextInputs:
        enc = self._tok.encode(normalise_caption(caption))
        ids = np.asarray(enc.ids, np.int64)
        tokens = tuple(enc.tokens)
        if ids.shape[0] > self.max_len:  # upstream truncates to max_text_len
            ids, tokens = ids[: self.max_len], tokens[: self.max_len]
        mask, pos = phrase_masks(ids, self.special_ids)
        n = ids.shape[0]
        return TextInputs(
            input_ids=ids[None],
            attention_mask=np.ones((1, n), bool),
            position_ids=pos[None],
            token_type_ids=np.zeros((1, n), np.int64),
            text_token_mask=mask[None],
            tokens=tokens,
        )


class GroundingDino:
    """Open-vocabulary box detector over one checked ONNX graph."""

    def __init__(self, manifest: GdinoManifest, options: Optional[SessionOptions] = None):
        self.manifest = manifest
        self.session = GraphSession(manifest.graph, options)
        cfg = manifest.config
        self.tokenizer = Tokenizer(manifest.vocab_path, cfg.max_text_len, cfg.special_ids)
        graph_hw = self.session.input_shape("img")[2:]
        pre = manifest.preprocess
        self.static_hw = tuple(graph_hw) if all(isinstance(d, int) for d in graph_hw) else None
        if self.static_hw is not None and self.static_hw != tuple(pre.size_hw):
            raise ModelError(
                f"model: input 'img' was traced at {graph_hw[0]}x{graph_hw[1]} but the "
                f"manifest's preprocess.size is {list(pre.size_hw)}; Grounding DINO graphs "
                "only run at the size they were traced at",
                manifest.graph.path,
            )
        self._text_cache: dict = {}

    def input_size(self, height: int, width: int) -> Tuple[int, int]:
        """The (height, width) a frame of this size enters the graph at.

        "keep_aspect" (upstream's loader): the frame's own keep-aspect size, which a graph
        traced at a fixed size must equal — otherwise :class:`ModelError` says which size to
        re-export at (or to declare ``preprocess.resize = "stretch"`` to accept the
        distortion). "stretch": the traced size, whatever the frame.
        """
        pre = self.manifest.preprocess
        if pre.resize == "stretch":
            return tuple(int(v) for v in (self.static_hw or pre.size_hw))
        want = keep_aspect_size(height, width, pre.short_side, pre.max_size)
        if self.static_hw is not None and want != self.static_hw:
            raise ModelError(
                f"model: traced at {self.static_hw[0]}x{self.static_hw[1]}, but Grounding DINO resizes a "
                f"{height}x{width} frame (height x width) to {want[0]}x{want[1]} (short side "
                f"{pre.short_side}, long side at most {pre.max_size}, aspect kept); re-export with "
                f"`cobgs export-onnx gdino ... --size {want[0]} {want[1]}`, or set "
                "groundingdino.preprocess.resize = \"stretch\" in manifest.json to accept stretched frames "
                "(detections then differ from upstream's)", self.manifest.graph.path)
        return want

    def check_frames(self, sizes_hw) -> None:
        """Refuse, before any work, frame sizes the graph cannot take as upstream would."""
        for hw in dict.fromkeys(tuple(int(v) for v in hw) for hw in sizes_hw):
            self.input_size(*hw)

    def text_inputs(self, caption: str) -> TextInputs:
        if caption not in self._text_cache:
            self._text_cache[caption] = self.tokenizer(caption)
        return self._text_cache[caption]

    def detect(
        self,
        rgb: np.ndarray,
        caption: str,
        box_threshold: float,
        text_threshold: float,
        order: str = "confidence",
    ) -> List[Detection]:
        """Detect ``caption`` in one RGB uint8 [H, W, 3] frame.

        ``order``: "confidence" (best first) or "query" (the order of the model's queries,
        as upstream's ``predict()`` returns them)."""
        if order not in ("confidence", "query"):
            raise ValueError(f"order must be 'confidence' or 'query', got {order!r}")
        text = self.text_inputs(caption)
        img = to_model_input(rgb, self.manifest.preprocess, self.input_size(*rgb.shape[:2]))
        out = self.session.run({
            "img": img,
            "input_ids": text.input_ids,
            "attention_mask": text.attention_mask,
            "position_ids": text.position_ids,
            "token_type_ids": text.token_type_ids,
            "text_token_mask": text.text_token_mask,
        })
        n = text.input_ids.shape[1]
        logits = out["logits"][0][:, :n].astype(np.float64)
        prob = 1.0 / (1.0 + np.exp(-logits))  # [Q, L]; positions past L are -inf anyway
        conf = prob.max(axis=1)
        keep = np.flatnonzero(conf > box_threshold)
        h, w = rgb.shape[:2]
        dets = []
        for q in (keep[np.argsort(-conf[keep], kind="stable")] if order == "confidence" else keep):
            cx, cy, bw, bh = (float(v) for v in out["boxes"][0, q])
            box = ((cx - bw / 2) * w, (cy - bh / 2) * h, (cx + bw / 2) * w, (cy + bh / 2) * h)
            dets.append(Detection(box, float(conf[q]), self._phrase(text, prob[q],
                                                                     text_threshold)))
        return dets

    def _phrase(self, text: TextInputs, prob: np.ndarray, text_threshold: float) -> str:
        special = set(self.tokenizer.special_ids)
        words = [
            t for t, i, p in zip(text.tokens, text.input_ids[0], prob)
            if p > text_threshold and int(i) not in special
        ]
        return " ".join(words).replace(" ##", "")
