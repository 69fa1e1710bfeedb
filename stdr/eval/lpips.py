"""LPIPS v0.1 (Zhang et al. 2018) without torchvision: the VGG16 / AlexNet trunks and the linear
heads are defined here and loaded from local files. Where no folder holds them, `fetch_weights`
downloads the official files once into the user cache (~/.cache/stdr/lpips), each checked
against its pinned SHA-256 (`stdr-data download lpips` does it ahead of time; the evaluation does
it on first use).

Weights (state dicts, loaded with weights_only=True) in one folder:
    vgg16_features.pth   or torchvision's cached vgg16-397923af.pth  (trunk, keys features.*)
    alexnet_features.pth or torchvision's cached alexnet-owt-7be5be79.pth
    lpips_v0.1_vgg_lin.pth / lpips_v0.1_alex_lin.pth, or the `lpips` package's v0.1/<net>.pth
Convention: inputs in [0, 1] are mapped to [-1, 1] (the official `normalize=True`) unless
input_range="[-1,1]" is turned off by passing input_range="[0,1]", which feeds [0, 1] images as
the 3DGS-family metric scripts do (their numbers are not comparable with the official ones).
"""
from __future__ import annotations

import importlib.util
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import torch
from torch import Tensor, nn

from ..ops import fixed_mean
from .. import user_cache
from ..data.fetch import DataError, download, sha256

_VGG_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_VGG_TAPS = (3, 8, 15, 22, 29)        # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (torchvision indices)
_VGG_CH = (64, 128, 256, 512, 512)
_ALEX_TAPS = (1, 4, 7, 9, 11)         # relu1..relu5
_ALEX_CH = (64, 192, 384, 256, 256)

TRUNK_FILES = {"vgg": ("vgg16_features.pth", "vgg16-397923af.pth"),
               "alex": ("alexnet_features.pth", "alexnet-owt-7be5be79.pth")}
LIN_FILES = {"vgg": ("lpips_v0.1_vgg_lin.pth", "vgg.pth"), "alex": ("lpips_v0.1_alex_lin.pth", "alex.pth")}


# The official files, SHA-256 pinned: torchvision's ImageNet weights (their names carry the first
# 8 hex digits of the SHA-256, torchvision's own check) and the LPIPS v0.1 linear heads of the
# authors' repository (the same bytes as lpips/weights/v0.1/*.pth in the `lpips` 0.1.4 wheel on PyPI,
# checked there).
_TV = "https://download.pytorch.org/models/"
_LIN = "https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/weights/v0.1/"
WEIGHT_SOURCES: dict[str, tuple[str, str, str]] = {  # file: (url, sha256, size for the message)
    "vgg16-397923af.pth": (_TV + "vgg16-397923af.pth",
                           "397923af8e79cdbb6a7127f12361acd7a2f83e06b05044ddf496e83de57a5bf0", "528 MB"),
    "alexnet-owt-7be5be79.pth": (_TV + "alexnet-owt-7be5be79.pth",
                                 "7be5be791159472b1fbf3c69796f7cb30dca7ad8466c2df70058c37116cdee02", "233 MB"),
    "vgg.pth": (_LIN + "vgg.pth", "a78928a0af1e5f0fcb1f3b9e8f8c3a2a5a3de244d830ad5c1feddc79b8432868", "7 KB"),
    "alex.pth": (_LIN + "alex.pth", "df73285e35b22355a2df87cdb6b70b343713b667eddbda73e1977e0c860835c0", "6 KB"),
}
FETCHED = {"vgg": ("vgg16-397923af.pth", "vgg.pth"), "alex": ("alexnet-owt-7be5be79.pth", "alex.pth")}


def fetch_dir() -> Path:
    """Where fetched weights go: the user cache's lpips folder (one of default_search_dirs)."""
    return user_cache() / "lpips"


def fetch_weights(net: str, dest: Optional[Path] = None, log=print) -> Path:
    """Download LPIPS-`net`'s official files into `dest` (default: fetch_dir()), each checked
    against its pinned SHA-256; files already there with the right hash are kept. Returns the
    folder. A failed or corrupted download raises stdr.data.fetch.DataError naming the file and
    leaves nothing in `dest` under the file's name."""
    if net not in FETCHED:
        raise ValueError(f"LPIPS net {net!r}: use 'vgg' or 'alex'")
    dest = Path(dest) if dest is not None else fetch_dir()
    dest.mkdir(parents=True, exist_ok=True)
    todo = [f for f in FETCHED[net] if not ((dest / f).is_file() and sha256(dest / f) == WEIGHT_SOURCES[f][1])]
    if todo:
        log(f"[stdr] LPIPS-{net} weights: downloading {', '.join(f'{f} ({WEIGHT_SOURCES[f][2]})' for f in todo)} "
            f"once into {dest} (SHA-256 checked)")
    for name in todo:
        url, want, _ = WEIGHT_SOURCES[name]
        tmp = dest / f".{name}.download"

        def pinned(path: Path, want=want) -> None:  # a body of unknown length is kept only with the pinned hash
            if sha256(path) != want:
                raise DataError(f"SHA-256 is not the pinned {want}")
        try:
            download([url], tmp, log=lambda m: None, verify=pinned)
        except DataError as e:
            why = str(e).split("\n")[1].strip() if "\n" in str(e) else str(e)  # "<url>: <reason>"
            raise DataError(f"LPIPS weights {name} could not be downloaded ({why}); offline? put the official "
                            f"file in {dest}") from None
        got = sha256(tmp)
        if got != want:
            tmp.unlink()
            raise DataError(f"LPIPS weights {name} from {url}: SHA-256 {got} is not the pinned {want}; the file "
                            "was corrupted in transfer or the source changed. Nothing was kept; run again, or put "
                            f"the official file in {dest} by hand")
        tmp.replace(dest / name)
    return dest


def _vgg16_features() -> nn.Sequential:
    layers, c = [], 3
    for v in _VGG_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, v, 3, padding=1), nn.ReLU(inplace=False)]
            c = v
    return nn.Sequential(*layers)


def _alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(), nn.MaxPool2d(3, 2))


def default_search_dirs() -> list[Path]:
    """Where LPIPS weights are looked for when eval.lpips_weights is not set: $STDR_LPIPS_WEIGHTS,
    the user cache ($XDG_CACHE_HOME/stdr/lpips, default ~/.cache/stdr/lpips), torch's hub cache,
    the `lpips` package. Never a path relative to the source (scripts/run.sh points
    STDR_LPIPS_WEIGHTS at a checkout's data/weights/lpips or ../shared/weights/lpips)."""
    dirs = []
    if os.environ.get("STDR_LPIPS_WEIGHTS"):
        dirs.append(Path(os.environ["STDR_LPIPS_WEIGHTS"]))
    dirs += [user_cache() / "lpips", Path(torch.hub.get_dir()) / "checkpoints"]
    spec = importlib.util.find_spec("lpips")  # the pip package ships the linear heads
    if spec is not None and spec.submodule_search_locations:
        dirs.append(Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1")
    return dirs


def _find(names, dirs) -> Optional[Path]:
    for d in dirs:
        for n in names:
            if (d / n).is_file():
                return d / n
    return None


@contextmanager
def _native_cpu_conv(device: torch.device):
    """On the CPU, convolutions without oneDNN (mkldnn): oneDNN's convolutions give other bits on
    other thread counts on some CPUs (measured: AMD EPYC, LPIPS-alex of one 200x200 pair, 1 thread
    against 2), torch's own do not, so LPIPS is the same on any thread count (tests/test_threads.py)."""
    if device.type != "cpu" or not torch.backends.mkldnn.enabled:
        yield
        return
    torch.backends.mkldnn.enabled = False
    try:
        yield
    finally:
        torch.backends.mkldnn.enabled = True


class LPIPS(nn.Module):
    def __init__(self, net: str = "vgg", weights_dir: Optional[str | Path] = None,
                 input_range: str = "[-1,1]"):
        super().__init__()
        if net not in TRUNK_FILES:
            raise ValueError(f"LPIPS net {net!r}: use 'vgg' or 'alex'")
        if input_range not in ("[-1,1]", "[0,1]"):
            raise ValueError(f"LPIPS input_range {input_range!r}: use '[-1,1]' (official) or '[0,1]'")
        self.net, self.input_range = net, input_range
        dirs = [Path(weights_dir)] if weights_dir else default_search_dirs()
        trunk_p, lin_p = _find(TRUNK_FILES[net], dirs), _find(LIN_FILES[net], dirs)
        if trunk_p is None or lin_p is None:
            missing = [f"{TRUNK_FILES[net][0]} (or {TRUNK_FILES[net][1]})"] if trunk_p is None else []
            missing += [f"{LIN_FILES[net][0]}"] if lin_p is None else []
            raise FileNotFoundError(
                f"LPIPS-{net} weights not found: missing {', '.join(missing)} in "
                f"{[str(d) for d in dirs]}. Put them in one folder and set eval.lpips_weights=<folder> "
                "(or STDR_LPIPS_WEIGHTS), or set eval.lpips=false to skip LPIPS.")
        self.features = _vgg16_features() if net == "vgg" else _alexnet_features()
        sd = torch.load(trunk_p, map_location="cpu", weights_only=True)
        sd = {k[len("features."):]: v for k, v in sd.items() if k.startswith("features.")}
        self.features.load_state_dict(sd)
        chans = _VGG_CH if net == "vgg" else _ALEX_CH
        self.lins = nn.ModuleList([nn.Conv2d(c, 1, 1, bias=False) for c in chans])
        lin = torch.load(lin_p, map_location="cpu", weights_only=True)
        for i, conv in enumerate(self.lins):
            conv.weight.data.copy_(lin[f"lin{i}.model.1.weight"])
        self.taps = _VGG_TAPS if net == "vgg" else _ALEX_TAPS
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.weight_files = (str(trunk_p), str(lin_p))
        self.eval().requires_grad_(False)

    def _feats(self, x: Tensor) -> list[Tensor]:
        out, h = [], (x - self.shift) / self.scale
        for i, layer in enumerate(self.features):
            h = layer(h)
            if i in self.taps:
                out.append(h)
            if i >= self.taps[-1]:
                break
        return out

    def forward(self, img1: Tensor, img2: Tensor) -> Tensor:
        """LPIPS distance per image pair; images [B, 3, H, W] (or [H, W, 3]) in [0, 1]."""
        if img1.dim() == 3:
            img1, img2 = img1.permute(2, 0, 1)[None], img2.permute(2, 0, 1)[None]
        if self.input_range == "[-1,1]":
            img1, img2 = img1 * 2 - 1, img2 * 2 - 1
        with _native_cpu_conv(img1.device):
            feats1, feats2 = list(self._feats(img1)), list(self._feats(img2))
        total = 0.0
        for lin, f1, f2 in zip(self.lins, feats1, feats2):
            n1 = f1 / (f1.square().sum(1, keepdim=True).sqrt() + 1e-10)
            n2 = f2 / (f2.square().sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + fixed_mean(lin((n1 - n2) ** 2), (2, 3))
        return total.view(-1)
