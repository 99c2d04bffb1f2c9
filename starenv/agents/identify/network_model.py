"""Paper 002's end-to-end identifier network (Han et al. 2021, Sec. 3): a raw smeared star image in, the index of
the navigation star on the boresight (the "main star") out.

Architecture (paper, Figs. 4-6 and Eqs. 6-11), every size a field of :class:`MainStarConfig`:

* preprocessing: the raw frame (DN) is area-resized to ``input_size`` (paper: 1024 -> 256) and its median (the
  background) subtracted, in numpy, before the network (:func:`starenv.datasets.preprocess.network_input`, shared by
  the dataset generator and the identifier); the network compresses its input as ``asinh(x / scale_dn)``.  The
  paper's "normalised with a mean and variance of 0.1" does not fix a scale for raw DN, so this is a choice.
  ``centre = "main_star"``: the input is shifted to put a star at its centre (the paper's training images have their
  main star there); the identifier puts each detection near the frame's centre there in turn.
* feature extractor: a 3x3 stem convolution, a stride-2 max-pool and six ResNet basic blocks (two 3x3 convolutions,
  BatchNorm, ReLU; a 1x1 projection shortcut where the shape changes), blocks 1, 3 and 5 with stride 2: four
  down-samplings, ``input_size / 16`` squared tokens of ``widths[-1]`` = D channels (paper: 256 -> 64 x 16 x 16).
* tokens: the feature map flattened to N tokens, a learnable positional embedding added to them, a learnable class
  ("semantic") token prepended without one (Eq. 6).
* encoder: ``depth`` pre-LayerNorm blocks (Eq. 10) of multi-head self-attention, each of the ``heads`` heads of
  dimension ``head_dim`` (Eq. 7-8 give each head the full D, which is what makes 6 heads with D = 64 well-defined;
  the paper's Eq. 9 omits the 1/sqrt(d) scaling, kept here as in every Transformer) and a GELU MLP of width
  ``mlp_dim`` (not given in the paper), with residuals.
* head: LayerNorm of the class token (Eq. 11), one linear layer over the navigation stars.

:func:`parameter_count` gives the parameter count in closed form from the config (tested against the module).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import torch
from torch import nn
from torch.nn import functional as F

# Bounds checked before a network is built (a config read from a file must not allocate without limit):
MAX_PARAMETERS = 2**27  # trainable parameters (512 MiB as float32; far above the paper's configuration)
MAX_INPUT_SIZE = 1024  # px: (1024 / 16)^2 = 4096 tokens, attention maps of 4096^2 per head (the paper: 256)
MAX_FIELD = 2**16  # any single size (classes, channels, depth, heads, dims)
CENTRES = ("frame", "main_star")
LATER_FIELDS = ("centre",)  # fields added after weights were first shipped: absent in a manifest means the default


@dataclass(frozen=True)
class MainStarConfig:
    """Sizes of the network; the defaults are the paper's where it gives them (``mlp_dim`` and ``widths`` except the
    last are not given; the paper's widths are in its Fig. 6 only)."""

    n_classes: int = 4331
    input_size: int = 256
    stem_width: int = 16
    widths: tuple[int, ...] = (16, 16, 32, 32, 64, 64)
    depth: int = 8
    heads: int = 6
    head_dim: int = 64
    mlp_dim: int = 256
    scale_dn: float = 10.0
    centre: str = "frame"  # what sits at the input's centre: "frame" (the whole frame resized) or "main_star"

    def __post_init__(self):
        def size(name: str, value) -> None:
            if type(value) is not int or not 1 <= value <= MAX_FIELD:
                raise ValueError(f"{name}: expected an integer in [1, {MAX_FIELD}], got {value!r}")

        if not isinstance(self.widths, tuple | list) or len(self.widths) != 6:
            raise ValueError(f"widths: expected 6 basic-block widths, got {self.widths!r}")
        for k, w in enumerate(self.widths):
            size(f"widths[{k}]", w)
        for name in ("n_classes", "input_size", "stem_width", "depth", "heads", "head_dim", "mlp_dim"):
            size(name, getattr(self, name))
        if self.input_size % 16 or self.input_size > MAX_INPUT_SIZE:
            raise ValueError(f"input_size: expected a multiple of 16 (four stride-2 stages) up to {MAX_INPUT_SIZE}, "
                             f"got {self.input_size}")
        if not (isinstance(self.scale_dn, int | float) and not isinstance(self.scale_dn, bool)
                and math.isfinite(self.scale_dn) and self.scale_dn > 0):
            raise ValueError(f"scale_dn: expected a positive number of DN, got {self.scale_dn!r}")
        if self.centre not in CENTRES:
            raise ValueError(f"centre: expected one of {', '.join(CENTRES)}, got {self.centre!r}")
        if parameter_count(self) > MAX_PARAMETERS:
            raise ValueError(f"config: {parameter_count(self)} parameters, more than {MAX_PARAMETERS}")

    @property
    def dim(self) -> int:
        """D, the token dimension: the last block's channels."""
        return self.widths[-1]

    @property
    def tokens(self) -> int:
        """N, the feature-map tokens (class token not counted)."""
        return (self.input_size // 16) ** 2

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        if self.centre == "frame":  # left out, so the manifests written before the field keep their identity
            d.pop("centre")
        return d

    @classmethod
    def from_dict(cls, d: dict) -> MainStarConfig:
        """A config from :meth:`to_dict`'s form; an unknown or missing field is a ValueError naming it."""
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(d) - set(names))
        missing = [n for n in names if n not in d and n not in LATER_FIELDS]
        if unknown or missing:
            raise ValueError(f"expected the fields {', '.join(names)}; unknown {unknown}, missing {missing}")
        widths = d["widths"]
        return cls(**{**d, "widths": tuple(widths) if isinstance(widths, list) else widths})


class BasicBlock(nn.Module):
    """ResNet basic block: conv3x3-BN-ReLU-conv3x3-BN, plus the (projected) input, ReLU."""

    def __init__(self, c_in: int, c_out: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.shortcut = nn.Identity()
        if stride != 1 or c_in != c_out:
            self.shortcut = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(y)) + self.shortcut(x))


class Attention(nn.Module):
    """Multi-head self-attention with ``heads`` heads of ``head_dim`` each (Eqs. 7-9)."""

    def __init__(self, dim: int, heads: int, head_dim: int):
        super().__init__()
        self.heads, self.head_dim = heads, head_dim
        self.qkv = nn.Linear(dim, 3 * heads * head_dim)
        self.out = nn.Linear(heads * head_dim, dim)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        b, n, _ = z.shape
        q, k, v = self.qkv(z).view(b, n, 3, self.heads, self.head_dim).permute(2, 0, 3, 1, 4)
        a = torch.softmax(q @ k.transpose(-1, -2) * self.head_dim**-0.5, dim=-1)
        return self.out((a @ v).transpose(1, 2).reshape(b, n, self.heads * self.head_dim))


class EncoderBlock(nn.Module):
    """Pre-LN Transformer block (Eq. 10): z' = MSA(LN(z)) + z; z = MLP(LN(z')) + z'."""

    def __init__(self, dim: int, heads: int, head_dim: int, mlp_dim: int):
        super().__init__()
        self.ln1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads, head_dim)
        self.ln2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, mlp_dim), nn.GELU(), nn.Linear(mlp_dim, dim))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        z = z + self.attn(self.ln1(z))
        return z + self.mlp(self.ln2(z))


class MainStarNet(nn.Module):
    """Network inputs (B, S, S) or (B, 1, S, S), S = ``input_size`` (DN above the background, as
    :func:`~starenv.datasets.preprocess.network_input` makes them from raw frames) -> class logits (B, n_classes)."""

    def __init__(self, config: MainStarConfig):
        super().__init__()
        self.config = c = config
        self.stem = nn.Sequential(nn.Conv2d(1, c.stem_width, 3, 1, 1, bias=False), nn.BatchNorm2d(c.stem_width),
                                  nn.ReLU(), nn.MaxPool2d(2))
        blocks, c_in = [], c.stem_width
        for i, width in enumerate(c.widths):
            blocks.append(BasicBlock(c_in, width, 2 if i in (0, 2, 4) else 1))
            c_in = width
        self.blocks = nn.Sequential(*blocks)
        self.pos = nn.Parameter(torch.zeros(1, c.tokens, c.dim))
        self.cls = nn.Parameter(torch.zeros(1, 1, c.dim))
        nn.init.trunc_normal_(self.pos, std=0.02)
        nn.init.trunc_normal_(self.cls, std=0.02)
        self.encoder = nn.Sequential(*[EncoderBlock(c.dim, c.heads, c.head_dim, c.mlp_dim) for _ in range(c.depth)])
        self.norm = nn.LayerNorm(c.dim)
        self.head = nn.Linear(c.dim, c.n_classes)

    def preprocess(self, inputs: torch.Tensor) -> torch.Tensor:
        """Network inputs (DN above the background) -> the compressed (B, 1, input_size, input_size) tensor;
        elementwise, so deterministic on every device."""
        x = inputs.float()
        if x.dim() == 3:
            x = x.unsqueeze(1)
        size = self.config.input_size
        if x.dim() != 4 or x.shape[1:] != (1, size, size):
            raise ValueError(f"MainStarNet: expected inputs (B, {size}, {size}) (network_input of the frames), got "
                             f"{tuple(inputs.shape)}")
        return torch.asinh(x / self.config.scale_dn)

    def features(self, frames: torch.Tensor) -> torch.Tensor:
        """The CNN's feature map (B, D, input_size / 16, input_size / 16)."""
        return self.blocks(self.stem(self.preprocess(frames)))

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        f = self.features(frames)
        tokens = f.flatten(2).transpose(1, 2) + self.pos
        z = torch.cat([self.cls.expand(len(tokens), -1, -1), tokens], dim=1)
        z = self.encoder(z)
        return self.head(self.norm(z[:, 0]))


def parameter_count(c: MainStarConfig) -> int:
    """Trainable parameters of :class:`MainStarNet` for config ``c``, in closed form."""
    bn = 2  # weight and bias per channel (running statistics are buffers)
    n = 9 * c.stem_width + bn * c.stem_width
    c_in = c.stem_width
    for i, w in enumerate(c.widths):
        n += 9 * c_in * w + bn * w + 9 * w * w + bn * w
        if i in (0, 2, 4) or c_in != w:
            n += c_in * w + bn * w
        c_in = w
    d, inner = c.dim, c.heads * c.head_dim
    per_block = 2 * 2 * d + (d * 3 * inner + 3 * inner) + (inner * d + d) + (d * c.mlp_dim + c.mlp_dim) + (
        c.mlp_dim * d + d)
    return n + c.tokens * d + d + c.depth * per_block + 2 * d + d * c.n_classes + c.n_classes
