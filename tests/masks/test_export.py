"""The export machinery, on stand-in modules with the contract's interfaces."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import onnx
import pytest
import torch
from torch import nn

from cobgs.masks.export import common
from cobgs.masks.export.common import ExportError, export_graph, verify_graph
from cobgs.masks.export.gdino_export import export_gdino
from cobgs.masks.gdino import GroundingDino
from cobgs.masks.manifest import load_manifest

from . import fakes, scenes


class Affine(nn.Module):
    def __init__(self, n=8):
        super().__init__()
        self.lin = nn.Linear(n, n)

    def forward(self, x, y):
        return self.lin(x) + y.sum(0, keepdim=True), x * 2


def test_export_and_verify_with_dynamic_axis(tmp_path):
    m = Affine()
    path = export_graph(m, (torch.randn(3, 8), torch.randn(5, 8)), tmp_path / "g.onnx",
                        ["x", "y"], ["a", "b"], {"y": {0: "n"}})
    model = onnx.load(str(path))
    assert model.opset_import[0].version == 17
    assert not list(tmp_path.glob(".export-*"))  # the private temp folder is gone
    # a different size on the dynamic axis than traced
    rep = verify_graph(path, m, {"x": np.ones((3, 8), np.float32),
                                 "y": np.ones((7, 8), np.float32)}, ["a", "b"])
    assert [p.name for p in rep] == ["a", "b"] and all(p.ok for p in rep)


def test_verify_reports_a_mismatch(tmp_path):
    m = Affine()
    path = export_graph(m, (torch.randn(3, 8), torch.randn(5, 8)), tmp_path / "g.onnx",
                        ["x", "y"], ["a", "b"])
    with torch.no_grad():
        m.lin.bias += 1.0  # the graph no longer matches the module
    with pytest.raises(ExportError, match=r"g.onnx: onnxruntime disagrees with PyTorch.*'a'"):
        verify_graph(path, m, {"x": np.ones((3, 8), np.float32),
                               "y": np.ones((5, 8), np.float32)}, ["a", "b"])


def test_large_weights_go_to_external_data(tmp_path, monkeypatch):
    monkeypatch.setattr(common, "PROTOBUF_LIMIT", (64 << 20) + 10)  # pretend 2 GB is tiny
    m = Affine(n=64)
    path = export_graph(m, (torch.randn(3, 64), torch.randn(5, 64)), tmp_path / "big.onnx",
                        ["x", "y"], ["a", "b"])
    data = tmp_path / "big.onnx.data"
    assert data.is_file() and data.stat().st_size >= 64 * 64 * 4
    rep = verify_graph(path, m, {"x": np.ones((3, 64), np.float32),
                                 "y": np.ones((5, 64), np.float32)}, ["a", "b"])
    assert all(p.ok for p in rep)


def test_gdino_export_writes_contract_files_and_manifest(tmp_path, models_dir):
    # a folder that already holds a SAM2 export: the manifest is merged, not replaced
    out = tmp_path / "models"
    fakes.build_sam2(out)
    vocab = tmp_path / "vocab.txt"
    fakes.write_vocab(vocab)
    stand_in = fakes.FakeDetector((48, 64), 144.0, fakes.WORDS["square"])
    rep = export_gdino(out, (48, 64), graph_module=stand_in, vocab_path=vocab,
                       caption="red square .", short_side=48)
    assert rep and all(p.ok for p in rep)
    assert (out / "groundingdino" / "groundingdino.onnx").is_file()
    assert (out / "groundingdino" / "vocab.txt").read_text() == vocab.read_text()
    data = json.loads((out / "manifest.json").read_text())
    assert set(data) >= {"sam2", "groundingdino"}
    assert data["groundingdino"]["shape"]["model"]["img"] == [1, 3, 48, 64]
    m = load_manifest(out)
    det = GroundingDino(m.gdino)
    img, _ = scenes.render(scenes.Frame("red"))
    assert det.detect(img, "red square", 0.3, 0.45)[0].confidence == pytest.approx(0.9)


def test_gdino_export_needs_config_and_checkpoint(tmp_path):
    with pytest.raises(ExportError, match="needs --config and --checkpoint"):
        export_gdino(tmp_path, (64, 64))


@pytest.mark.skipif(importlib.util.find_spec("sam2") is not None,
                    reason="sam2 is installed here: the missing-package path cannot be shown")
def test_missing_sam2_package_is_a_clear_error(tmp_path):
    from cobgs.masks.export.sam2_export import export_sam2

    with pytest.raises(ExportError, match=r"needs the Python package 'sam2.build_sam'.*"
                                          r"git\+https://github.com/facebookresearch/sam2.git@2b90b9f.*"
                                          r"not Meta's upload"):
        export_sam2("configs/sam2.1/sam2.1_hiera_t.yaml", None, tmp_path)
    assert not (tmp_path / "manifest.json").exists()


def test_cli_registered_and_lazy():
    import subprocess
    import sys

    # only this provider is checked: the others belong to other modules
    code = ("import argparse, sys, stages.commands.onnx as m; "
            "m.register(argparse.ArgumentParser().add_subparsers()); "
            "print(any(k in sys.modules for k in ('onnxruntime', 'torch', 'sam2')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"  # `cobgs --help` stays fast
    from stages.commands.cli import PROVIDERS, main

    assert "stages.commands.onnx" in PROVIDERS
    with pytest.raises(SystemExit):
        main(["export-onnx", "sam2", "--help"])


def test_cli_missing_checkpoint_reports_one_line(tmp_path, capsys):
    from stages.commands.cli import main

    rc = main(["export-onnx", "gdino", "--config", str(tmp_path / "c.py"), "--checkpoint",
               str(tmp_path / "w.pth"), "--out", str(tmp_path / "o")])
    assert rc == 1
    err = capsys.readouterr().err
    assert "cobgs export-onnx: error:" in err and ("groundingdino" in err or "not found" in err)


def test_gdino_export_refuses_transformers_5_saying_which_works(monkeypatch):
    import sys
    import types

    from cobgs.masks.export.gdino_export import check_transformers

    monkeypatch.setitem(sys.modules, "transformers", types.SimpleNamespace(__version__="5.0.1"))
    with pytest.raises(ExportError, match=r"transformers 5.0.1 .*get_extended_attention_mask.*<5.*4.57.6"):
        check_transformers()
    monkeypatch.setitem(sys.modules, "transformers", types.SimpleNamespace(__version__="4.57.6"))
    check_transformers()
