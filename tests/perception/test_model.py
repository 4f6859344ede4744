"""The training side (torch) and the runtime side (ONNX) agree; skipped where torch is not installed."""

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")


def test_tiny_model_exports_to_onnx_and_decodes_like_torch(tmp_path: Path):
    from macroloc.perception.detector import Detector, DetectorSpec
    from macroloc.perception.model import STRIDE_PX, TinyYolo

    torch.manual_seed(0)
    model = TinyYolo(n_anchors=2, n_classes=3).eval()
    x = torch.rand(1, 3, 96, 128)
    path = tmp_path / "tiny.onnx"
    torch.onnx.export(model, (x,), str(path), input_names=["image"], output_names=["raw"], opset_version=13,
                      dynamo=False)
    spec = DetectorSpec(input_wh=(128, 96), stride_px=STRIDE_PX, anchors_px=((16.0, 32.0), (40.0, 20.0)))
    image = (x[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    raw, box = Detector(path, spec).raw(image)
    with torch.no_grad():
        expected = model(torch.from_numpy(image.astype(np.float32) / 255).permute(2, 0, 1)[None])[0].numpy()
    assert box.scale == 1.0 and raw.shape == (2 * 8, 6, 8)
    assert np.allclose(raw, expected, atol=1e-4)


def test_loss_targets_and_one_gradient_step():
    from macroloc.perception.model import STRIDE_PX, TinyYolo
    from macroloc.perception.train import build_targets, yolo_loss

    anchors = np.array([[16.0, 32.0], [48.0, 24.0]])
    boxes = [np.array([[20.0, 10.0, 36.0, 42.0]]), np.zeros((0, 4))]
    t = build_targets(boxes, [np.array([1]), np.zeros(0, np.int64)], anchors, (6, 8), STRIDE_PX)
    assert t["pos"].sum() == 1 and t["pos"][0, 0, 1, 1]  # centre (28, 26) -> cell (row 1, col 1), tall anchor
    assert np.allclose(t["txy"][0, 0, :, 1, 1], [28 / 16 - 1, 26 / 16 - 1])
    model = TinyYolo(2, 3)
    loss = yolo_loss(model(torch.rand(2, 3, 96, 128)), t, boxes, anchors, STRIDE_PX)
    loss.backward()
    assert np.isfinite(float(loss)) and model.head.weight.grad is not None


def test_onnx_equals_torch_on_a_batch(tmp_path: Path):
    import onnxruntime as ort

    from macroloc.perception.model import TinyYolo

    torch.manual_seed(1)
    model = TinyYolo(n_anchors=3, n_classes=3, width=2).eval()
    x = torch.rand(4, 3, 64, 96)
    path = tmp_path / "batch.onnx"
    torch.onnx.export(model, (x[:1],), str(path), input_names=["image"], output_names=["raw"], opset_version=13,
                      dynamo=False, dynamic_axes={"image": {0: "n"}, "raw": {0: "n"}})
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"image": x.numpy()})[0]
    with torch.no_grad():
        expected = model(x).numpy()
    assert got.shape == (4, 3 * 8, 4, 6)
    assert np.allclose(got, expected, atol=1e-4)


def test_real_shares_fill_the_batch_from_the_sets_present():
    from macroloc.perception.train import real_shares

    assert real_shares(16, 0.6, True, True) == (10, 6)
    assert real_shares(8, 0.6, False, True) == (0, 8) and real_shares(8, 0.6, True, False) == (8, 0)
