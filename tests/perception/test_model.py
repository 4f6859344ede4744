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


def test_batch_shares_fill_every_slot_in_proportion():
    from macroloc.perception.train import batch_shares

    assert batch_shares(16, {"a": 0.6, "b": 0.4}) == {"a": 10, "b": 6}
    assert batch_shares(10, {"a": 1.0, "b": 1.0, "c": 1.0}) in ({"a": 4, "b": 3, "c": 3}, {"a": 3, "b": 4, "c": 3},
                                                                 {"a": 3, "b": 3, "c": 4})
    assert sum(batch_shares(7, {"a": 0.33, "b": 0.33, "c": 0.34}).values()) == 7


def test_source_weights_give_the_indoor_share_by_square_root_and_the_rest_to_facades():
    from macroloc.perception.train import source_weights

    real = {"robot_door_detection": {"train": [0] * 400}, "fisheye_robot": {"train": [0] * 100},
            "facades": {"train": [0] * 50}}
    w = source_weights(real, 0.6)  # type: ignore[arg-type]
    assert w["robot_door_detection"] == pytest.approx(0.4) and w["fisheye_robot"] == pytest.approx(0.2)
    assert w["facades"] == pytest.approx(0.4)
    only_indoor = source_weights({"fisheye_robot": {"train": [0] * 9}}, 0.6)  # type: ignore[dict-item]
    assert only_indoor == {"fisheye_robot": pytest.approx(1.0)}


def test_pretrained_network_exports_to_onnx_equal_to_torch(tmp_path: Path):
    import onnxruntime as ort

    from macroloc.perception.backbone import ShuffleYolo

    torch.manual_seed(2)
    model = ShuffleYolo(n_anchors=5, n_classes=3)
    with torch.no_grad():  # batch-norm statistics away from (0, 1): the export must carry them
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
    model.eval()
    x = torch.rand(2, 3, 240, 320)
    path = tmp_path / "shuffle.onnx"
    torch.onnx.export(model, (x[:1],), str(path), input_names=["image"], output_names=["raw"], opset_version=13,
                      dynamo=False)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = np.concatenate([session.run(None, {"image": x[i:i + 1].numpy()})[0] for i in range(2)])
    with torch.no_grad():
        expected = model(x).numpy()
    assert got.shape == (2, 5 * 8, 15, 20)  # stride 16 on 320 x 240, as the runtime's decoder expects
    assert np.allclose(got, expected, atol=1e-4)


def test_pretrained_weights_load_exactly_and_a_wrong_file_is_refused(tmp_path: Path):
    from macroloc.perception.backbone import ShuffleYolo
    from tests.conftest import shared_data

    weights = shared_data("../weights/fastestdet_coco/fastestdet_coco.pth")
    state = torch.load(weights, map_location="cpu", weights_only=True)
    model = ShuffleYolo(5, 3)
    loaded = model.load_pretrained(weights)
    own = model.state_dict()
    assert len(loaded) == sum(1 for k in state if k.split(".")[0] in ("backbone", "SPP"))
    assert all(torch.equal(own[k], state[k]) for k in loaded)
    assert not any(k.startswith("head") for k in loaded)  # the COCO head is not the door head
    backbone_only = ShuffleYolo(5, 3).load_pretrained(weights.parent / "shufflenetv2_0.5x_imagenet_backbone.pth")
    assert backbone_only and all(k.startswith("backbone.") for k in backbone_only)
    torch.save({"conv.weight": torch.zeros(3)}, tmp_path / "other.pth")
    with pytest.raises(ValueError, match="expected layout"):
        ShuffleYolo(5, 3).load_pretrained(tmp_path / "other.pth")
