"""Single-byte flips of saved primitives, segmentations and skill libraries are caught on load (issue 11).

Every byte of the tensor payload of a saved primitive is flipped (a seeded sample of 200 bytes for the larger
segmentation and library files), and every byte of the metadata pickle: a payload flip must raise StoreError
naming the file; a metadata flip must raise StoreError naming the file or load content identical to what was saved
(the pickle protocol byte and memo indices do not change the content).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from lfd_torch.ds import fit_lpvds, load_primitive
from lfd_torch.errors import StoreError
from lfd_torch.gmm import EMFitter
from lfd_torch.segmentation import FixedSegmenter, Segmentation
from lfd_torch.segmentation.synthetic import multi_step_demos
from lfd_torch.skills import SkillLibrary
from lfd_torch.store.checksum import payload_digest, zip_member_spans

F64 = torch.float64


@pytest.fixture(scope="module")
def saved(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    corners = torch.tensor([[-1.0, 1.0], [-1.0, 0.0], [0.0, 0.0]], dtype=F64)
    demos = multi_step_demos(torch.Generator().manual_seed(0), n_demos=2, waypoints=corners, samples_per_step=25,
                             timing_jitter=0.0).demos  # fmt: skip
    seg = FixedSegmenter([0.5])(demos)
    lib = SkillLibrary.learn(demos, seg, generator=torch.Generator().manual_seed(1), check=False)
    prim = fit_lpvds(demos, gmm=EMFitter(n_components=2, max_iter=10), generator=torch.Generator().manual_seed(2))
    root = tmp_path_factory.mktemp("flips")
    lib.save(root / "library")
    return {"primitive": prim.save(root / "primitive.pt"), "segmentation": seg.save(root / "segmentation.pt"),
            "library": root / "library"}  # fmt: skip


def _positions(path: Path, n_payload: int | None, seed: int) -> tuple[list[int], list[int]]:
    """(payload positions: all, or a seeded sample of n_payload; every metadata-pickle position)."""
    spans = zip_member_spans(path)
    payload = [p for name, (a, b) in spans.items() if "/data/" in name for p in range(a, b)]
    header = [p for name, (a, b) in spans.items() if name.endswith("data.pkl") for p in range(a, b)]
    assert payload and header, f"{path} has no payload or no metadata pickle: {list(spans)}"
    if n_payload is not None and n_payload < len(payload):
        payload = sorted(np.random.default_rng(seed).choice(payload, size=n_payload, replace=False).tolist())
    return payload, header


def _flip_all(path: Path, load, content, positions: list[int], *, allow_identical: bool, seed: int) -> dict[str, int]:
    """Flip each position in turn (XOR a seeded non-zero byte), load, restore; count detected / identical loads."""
    raw = path.read_bytes()
    reference = content(load())
    rng = np.random.default_rng(seed)
    counts = {"detected": 0, "identical": 0}
    try:
        for pos in positions:
            mutated = bytearray(raw)
            mutated[pos] ^= int(rng.integers(1, 256))
            path.write_bytes(bytes(mutated))
            try:
                out = load()
            except StoreError as exc:
                assert path.name in str(exc), f"byte {pos}: the StoreError does not name {path.name}: {exc}"
                counts["detected"] += 1
                continue
            assert allow_identical, f"a flip of payload byte {pos} of {path.name} loaded without error"
            assert content(out) == reference, f"a flip of metadata byte {pos} of {path.name} loaded changed content"
            counts["identical"] += 1
    finally:
        path.write_bytes(raw)
    assert content(load()) == reference  # the file is restored
    return counts


def _state(obj) -> str:
    return payload_digest(obj.state_dict())


def _library_state(lib: SkillLibrary) -> str:
    return payload_digest({"segmentation": lib.segmentation.state_dict(),
                           "skills": [{"p": s.primitive.state_dict(), "h2": s.h2_ref, "x": s.train_positions,
                                       "speed": s.speed, "duration": s.duration} for s in lib.skills]})  # fmt: skip


def test_every_payload_byte_and_metadata_byte_of_a_primitive(saved) -> None:
    path = saved["primitive"]
    payload, header = _positions(path, None, 0)

    def load():
        return load_primitive(path)

    out = _flip_all(path, load, _state, payload, allow_identical=False, seed=1)
    assert out["detected"] == len(payload)  # every one of the payload bytes
    out = _flip_all(path, load, _state, header, allow_identical=True, seed=2)
    assert out["detected"] + out["identical"] == len(header)
    assert out["detected"] > 0.9 * len(header)


def test_payload_sample_and_every_metadata_byte_of_a_segmentation(saved) -> None:
    path = saved["segmentation"]
    payload, header = _positions(path, 200, 3)

    def load():
        return Segmentation.load(path)

    assert _flip_all(path, load, _state, payload, allow_identical=False, seed=4)["detected"] == 200
    out = _flip_all(path, load, _state, header, allow_identical=True, seed=5)
    assert out["detected"] + out["identical"] == len(header)


@pytest.mark.parametrize("name", ["skills.pt", "step_0.pt", "segmentation.pt"])
def test_payload_sample_and_every_metadata_byte_of_a_library_file(saved, name: str) -> None:
    root = saved["library"]
    path = root / name
    payload, header = _positions(path, 200, 6)

    def load():
        return SkillLibrary.load(root)

    assert _flip_all(path, load, _library_state, payload, allow_identical=False, seed=7)["detected"] == len(payload)
    # the manifest holds a SHA-256 of every file: even a flip of the pickle protocol byte is detected
    assert _flip_all(path, load, _library_state, header, allow_identical=False, seed=8)["detected"] == len(header)


def test_flip_positions_cover_the_whole_payload(saved) -> None:
    """The spans are the tensor bytes: the payload of a primitive file is exactly its tensors' bytes."""
    path = saved["primitive"]
    spans = zip_member_spans(path)
    n_payload = sum(b - a for name, (a, b) in spans.items() if "/data/" in name)
    state = torch.load(path, weights_only=True)

    def nbytes(obj) -> int:
        if isinstance(obj, torch.Tensor):
            assert obj.untyped_storage().nbytes() == obj.numel() * obj.element_size()  # compact: no unused bytes
            return obj.untyped_storage().nbytes()
        if isinstance(obj, dict):
            return sum(nbytes(v) for v in obj.values())
        return 0

    assert n_payload == nbytes(state)
    with pytest.raises(StoreError, match="not a torch zip"):
        zip_member_spans(path.with_suffix(".missing"))


def test_digest_sees_shape_dtype_and_structure() -> None:
    """Edits that keep the payload bytes but change their meaning change the digest: a reshaped tensor, another
    dtype of the same bytes, a renamed key, a tensor moved into a nested mapping."""
    t = torch.arange(6, dtype=torch.float64)
    base = payload_digest({"a": t, "b": 1})
    edited = [
        {"a": t.reshape(2, 3), "b": 1},
        {"a": t.view(torch.int64), "b": 1},
        {"c": t, "b": 1},
        {"a": {"a": t}, "b": 1},
        {"a": t, "b": "1"},
    ]
    digests = [payload_digest(e) for e in edited]
    assert base not in digests and len(set(digests)) == len(digests)
    assert payload_digest({"b": 1, "a": t.clone()}) == base  # key order and storage do not matter
