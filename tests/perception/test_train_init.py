"""`perception.train --init`: fine-tuning starts from the given weights (and their anchors), exactly."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")


def _photos(root: Path, n: int = 12) -> Path:
    """A tiny facade-style set: img_1..img_n with one window and one door each (YOLO labels)."""
    rng = np.random.default_rng(0)
    (root / "images").mkdir(parents=True)
    (root / "labels").mkdir()
    for i in range(1, n + 1):
        image = rng.integers(0, 255, (120, 160, 3), np.uint8)
        cv2.rectangle(image, (20, 20), (60, 50), (255, 255, 255), -1)
        cv2.rectangle(image, (90, 30), (120, 110), (0, 0, 0), -1)
        cv2.imwrite(str(root / "images" / f"img_{i}.jpg"), image)
        (root / "labels" / f"img_{i}.txt").write_text("0 0.25 0.292 0.25 0.25\n1 0.656 0.583 0.1875 0.667\n")
    return root


def _init_checkpoint(path: Path):  # type: ignore[no-untyped-def]
    from macroloc.perception.model import TinyYolo
    from macroloc.perception.train import N_ANCHORS

    torch.manual_seed(3)
    model = TinyYolo(N_ANCHORS, 3, 1)
    with torch.no_grad():  # batch-norm statistics away from (0, 1): the export must carry them
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.1, 0.1)
    anchors = np.array([[12.0, 20.0], [30.0, 40.0], [60.0, 90.0], [100.0, 150.0], [200.0, 220.0]])
    torch.save({"ema": model.state_dict(), "anchors": anchors, "width": 1, "steps": 7}, path)
    return model.eval(), anchors


@pytest.mark.slow
def test_init_exports_the_init_weights_unchanged(tmp_path: Path) -> None:
    import onnxruntime as ort

    from macroloc.perception.train import load_init, main

    model, anchors = _init_checkpoint(tmp_path / "init.pt")
    photos = _photos(tmp_path / "facades")
    out = tmp_path / "out"
    main(["--init", str(tmp_path / "init.pt"), "--steps", "0", "--facades", str(photos), "--indoor",
          str(tmp_path / "no_indoor"), "--out", str(out), "--report", str(tmp_path / "report")])
    x = torch.rand(3, 3, 240, 320, generator=torch.Generator().manual_seed(5))
    session = ort.InferenceSession(str(out / "detector.onnx"), providers=["CPUExecutionProvider"])
    got = np.concatenate([session.run(None, {"image": x[i:i + 1].numpy()})[0] for i in range(len(x))])
    with torch.no_grad():
        expected = model(x).numpy()
    assert np.allclose(got, expected, atol=1e-4)
    sidecar = json.loads((out / "detector.json").read_text())
    assert np.allclose(sidecar["anchors_px"], anchors)  # the head is tied to the init's anchors
    assert sidecar["training"]["init"]["path"] == str(tmp_path / "init.pt")
    assert sidecar["training"]["init"]["steps"] == 7
    again, again_anchors, _ = load_init(out / "detector.pt")  # the weights beside the ONNX start the next run
    with torch.no_grad():
        assert np.allclose(again(x).numpy(), expected, atol=1e-5)
    assert np.allclose(again_anchors, anchors)


def test_init_rejects_a_file_without_weights(tmp_path: Path) -> None:
    from macroloc.perception.train import load_init

    torch.save({"something": 1}, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match="not a detector checkpoint"):
        load_init(tmp_path / "bad.pt")


def test_shipped_weights_are_the_shipped_onnx() -> None:
    import onnxruntime as ort

    from macroloc.perception.detector import DEFAULT_MODEL
    from macroloc.perception.train import SHIPPED_WEIGHTS, load_init

    model, anchors, _ = load_init(SHIPPED_WEIGHTS)
    sidecar = json.loads(Path(DEFAULT_MODEL).with_suffix(".json").read_text())
    assert np.allclose(anchors, sidecar["anchors_px"])
    x = torch.rand(1, 3, 240, 320, generator=torch.Generator().manual_seed(2))
    got = ort.InferenceSession(str(DEFAULT_MODEL), providers=["CPUExecutionProvider"]).run(None, {"image": x.numpy()})
    with torch.no_grad():
        assert np.allclose(got[0], model(x).numpy(), atol=1e-4)


def test_a_run_stopped_and_resumed_ends_as_the_run_in_one_go(tmp_path: Path) -> None:
    """A long training in parts (`--stop-at`, then `--resume`) gives the same weights, bit for bit."""
    from macroloc.perception.train import main

    photos = _photos(tmp_path / "facades")
    common = ["--steps", "24", "--batch", "4", "--save-every", "5", "--mosaic", "0.5", "--camera", "0.5",
              "--facades", str(photos), "--indoor", str(tmp_path / "no_indoor"), "--threads", "1"]
    main([*common, "--out", str(tmp_path / "whole"), "--report", str(tmp_path / "whole")])
    main([*common, "--out", str(tmp_path / "parts"), "--report", str(tmp_path / "parts"), "--stop-at", "11"])
    assert not (tmp_path / "parts" / "detector.onnx").exists()  # stopped: nothing exported yet
    assert torch.load(tmp_path / "parts" / "state.pt", weights_only=False)["step"] == 11
    main(["--resume", "--out", str(tmp_path / "parts"), "--report", str(tmp_path / "parts"), "--threads", "1"])
    whole = torch.load(tmp_path / "whole" / "detector.pt", weights_only=False)
    parts = torch.load(tmp_path / "parts" / "detector.pt", weights_only=False)
    assert whole["steps"] == parts["steps"] == 24
    for k, v in whole["ema"].items():
        assert torch.equal(v, parts["ema"][k]), k


def test_resume_without_a_saved_state_says_so(tmp_path: Path) -> None:
    from macroloc.perception.train import main

    with pytest.raises(SystemExit, match="no saved run state"):
        main(["--resume", "--report", str(tmp_path / "nothing")])
