"""Importing the DeepBasis authors' weights: every tensor lands in its place; bad files fail clearly, safely."""

from __future__ import annotations

import pickle

import pytest
import torch

from mideepbasis.model.checkpoint import CheckpointError, import_authors_weights, load_model, read_checkpoint


def nafblock(prefix: str, c: int) -> dict:
    return {f"{prefix}.conv1.weight": (2 * c, c, 1, 1), f"{prefix}.conv1.bias": (2 * c,),
            f"{prefix}.conv2.weight": (2 * c, 1, 3, 3), f"{prefix}.conv2.bias": (2 * c,),
            f"{prefix}.conv3.weight": (c, c, 1, 1), f"{prefix}.conv3.bias": (c,),
            f"{prefix}.sca.1.weight": (c, c, 1, 1), f"{prefix}.sca.1.bias": (c,),
            f"{prefix}.conv4.weight": (2 * c, c, 1, 1), f"{prefix}.conv4.bias": (2 * c,),
            f"{prefix}.conv5.weight": (c, c, 1, 1), f"{prefix}.conv5.bias": (c,),
            f"{prefix}.norm1.weight": (c,), f"{prefix}.norm1.bias": (c,),
            f"{prefix}.norm2.weight": (c,), f"{prefix}.norm2.bias": (c,),
            f"{prefix}.beta": (1, c, 1, 1), f"{prefix}.gamma": (1, c, 1, 1)}


def authors_layout() -> tuple[dict, dict]:
    """Names and shapes of the authors' GlobalNet and LocalNet state dicts, written from the
    description of their networks (channel lists, module nesting), not from our modules."""
    en = [9, 64, 128, 256, 512, 512, 512, 512, 512]
    de = [512, 512, 512, 512, 512, 256, 128, 64, 10]
    basis = [512, 512, 512, 512, 100]
    shapes = {}
    last_fc = None
    for i in range(8):
        in_c, out_c = en[i], en[i + 1]
        fc_out = en[i + 2] if i < 7 else en[8]
        conv = "basisNet.en_convs.0" if i == 0 else f"basisNet.en_convs.{i}.1"
        shapes[f"{conv}.weight"], shapes[f"{conv}.bias"] = (out_c, in_c, 4, 4), (out_c,)
        fc_in = in_c if i == 0 else out_c + last_fc
        shapes[f"basisNet.en_fcs.{i}.0.weight"], shapes[f"basisNet.en_fcs.{i}.0.bias"] = (fc_out, fc_in), (fc_out,)
        if i > 0:
            shapes[f"basisNet.en_g2e_fcs.{i - 1}.weight"] = (out_c, out_c)
        if 0 < i < 7:
            shapes[f"basisNet.en_ins_norms.{i - 1}.weight"] = shapes[f"basisNet.en_ins_norms.{i - 1}.bias"] = (out_c,)
        last_fc = fc_out
    for i in range(8):
        in_c, out_c = de[i] * (2 if i else 1), de[i + 1]
        for j, c in ((1, in_c), (2, out_c)):
            shapes[f"basisNet.weight_net.deconv.{i}.{j}.weight"] = (out_c, c, 3, 3)
            shapes[f"basisNet.weight_net.deconv.{i}.{j}.bias"] = (out_c,)
        if i != 7:
            shapes[f"basisNet.weight_net.ins.{i}.weight"] = shapes[f"basisNet.weight_net.ins.{i}.bias"] = (out_c,)
            shapes[f"basisNet.weight_net.fcs.{i}.0.weight"] = (out_c, out_c + last_fc)
            shapes[f"basisNet.weight_net.fcs.{i}.0.bias"] = (out_c,)
        shapes[f"basisNet.weight_net.f2c.{i}.weight"] = (out_c, last_fc)
        last_fc = out_c
    for i in range(4):
        shapes[f"basisNet.basis_net.{i}.0.weight"] = (basis[i + 1], basis[i])
        shapes[f"basisNet.basis_net.{i}.0.bias"] = (basis[i + 1],)

    local = {"intro.weight": (16, 122, 3, 3), "intro.bias": (16,), "ending.weight": (100, 16, 3, 3), "ending.bias": (100,)}
    c = 16
    for i, blocks in enumerate((2, 2, 4, 8)):
        for j in range(blocks):
            local.update(nafblock(f"encoders.{i}.{j}", c))
        local[f"downs.{i}.weight"], local[f"downs.{i}.bias"] = (2 * c, c, 2, 2), (2 * c,)
        c *= 2
    for j in range(12):
        local.update(nafblock(f"middle_blks.{j}", c))
    for i, blocks in enumerate((2, 2, 2, 2)):
        local[f"ups.{i}.0.weight"] = (2 * c, c, 1, 1)
        c //= 2
        for j in range(blocks):
            local.update(nafblock(f"decoders.{i}.{j}", c))
    return shapes, local


def write_weights(folder, drop: str | None = None, reshape: str | None = None):
    generator = torch.Generator().manual_seed(7)
    files = []
    for name, layout in zip(("net_g_2.414.pth", "net_l_2.414.pth"), authors_layout()):
        state = {}
        for key, shape in layout.items():
            if key == drop:
                continue
            if key == reshape:
                shape = (shape[0] + 1,) + tuple(shape[1:])
            state[key] = torch.randn(shape, generator=generator) * 0.02
        path = folder / name
        torch.save({"params": state}, path)
        files.append(path)
    return files


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    folder = tmp_path_factory.mktemp("authors")
    global_file, local_file = write_weights(folder)
    output = import_authors_weights(global_file, local_file, 45.0, folder / "imported.safetensors")
    return global_file, local_file, output


def test_every_tensor_lands_in_its_place(imported):
    global_file, local_file, output = imported
    model = load_model(output)
    theirs_global = torch.load(global_file, weights_only=True)["params"]
    theirs_local = torch.load(local_file, weights_only=True)["params"]
    assert len(model.state_dict()) == len(theirs_global) + len(theirs_local)
    checks = {
        "basisNet.en_convs.0.weight": model.encoder.convs[0].weight,
        "basisNet.en_convs.3.1.weight": model.encoder.convs[3].weight,
        "basisNet.en_fcs.7.0.bias": model.encoder.global_fcs[7].bias,
        "basisNet.en_g2e_fcs.2.weight": model.encoder.global_to_maps[2].weight,
        "basisNet.en_ins_norms.5.weight": model.encoder.norms[5].weight,
        "basisNet.weight_net.deconv.2.2.bias": model.weight_decoder.convs[2][1].bias,
        "basisNet.weight_net.deconv.7.1.weight": model.weight_decoder.convs[7][0].weight,
        "basisNet.weight_net.f2c.7.weight": model.weight_decoder.global_to_maps[7].weight,
        "basisNet.weight_net.fcs.0.0.weight": model.weight_decoder.global_fcs[0].weight,
        "basisNet.basis_net.3.0.weight": model.global_unit[6].weight,
    }
    for name, ours in checks.items():
        assert torch.equal(theirs_global[name], ours.detach()), name
    for name, ours in {"middle_blks.5.conv2.weight": model.local_unit.middle_blks[5].conv2.weight,
                       "ups.1.0.weight": model.local_unit.ups[1][0].weight,
                       "encoders.3.7.gamma": model.local_unit.encoders[3][7].gamma,
                       "intro.weight": model.local_unit.intro.weight}.items():
        assert torch.equal(theirs_local[name], ours.detach()), name


def test_checkpoint_records_convention_fov_and_sources(imported):
    global_file, local_file, output = imported
    document, _ = read_checkpoint(output)
    assert document["convention"] == "deepbasis" and document["fov_deg"] == 45.0
    assert document["network"]["plane_extent"] == pytest.approx(384 / 383)
    import hashlib

    assert document["provenance"]["global_sha256"] == hashlib.sha256(global_file.read_bytes()).hexdigest()
    assert document["provenance"]["local_sha256"] == hashlib.sha256(local_file.read_bytes()).hexdigest()


def test_missing_tensor_is_named(tmp_path):
    global_file, local_file = write_weights(tmp_path, drop="basisNet.weight_net.ins.3.bias")
    with pytest.raises(CheckpointError, match=r"net_g_2.414.pth: tensor basisNet.weight_net.ins.3.bias is missing"):
        import_authors_weights(global_file, local_file, 45.0, tmp_path / "out.safetensors")
    assert not (tmp_path / "out.safetensors").exists()


def test_wrong_shape_is_named(tmp_path):
    global_file, local_file = write_weights(tmp_path, reshape="middle_blks.2.conv3.weight")
    with pytest.raises(CheckpointError, match=r"tensor middle_blks.2.conv3.weight has shape \(257, 256, 1, 1\)"):
        import_authors_weights(global_file, local_file, 45.0, tmp_path / "out.safetensors")


class Trap:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_a_file_that_is_not_a_state_dict_fails_without_unpickling(tmp_path):
    marker = tmp_path / "unpickled"
    bad = tmp_path / "net_g_bad.pth"
    bad.write_bytes(pickle.dumps({"params": Trap(str(marker))}))
    _, local_file = write_weights(tmp_path)
    with pytest.raises(CheckpointError, match="net_g_bad.pth: not a PyTorch state dict"):
        import_authors_weights(bad, local_file, 45.0, tmp_path / "out.safetensors")
    assert not marker.exists()
    torch.save({"params": {"x": "not a tensor"}}, tmp_path / "strings.pth")
    with pytest.raises(CheckpointError, match="strings.pth: not a state dict"):
        import_authors_weights(tmp_path / "strings.pth", local_file, 45.0, tmp_path / "out.safetensors")
