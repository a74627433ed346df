"""Choreomusical networks (ChoreoMaster §3, Appendix A Tables 7–8), small enough for CPU.

Style (32-d, one space for both modalities):

- ``MusicStyleNet`` E_M: ``(N, 1, 96, 800)`` log-mel (dB) of an 8-s window → four conv blocks →
  two GRU layers → ``(N, 32)``.
- ``DanceStyleNet`` E_D: ``(N, 3, 18, 240)`` positions (m) of the 18 main joints over 8 s at 30 fps
  → graph-convolution blocks over the skeleton's joint graph (``JOINT_EDGES``) → two GRU layers →
  ``(N, 32)``.
- ``StyleModel``: both encoders, a classification head per branch and a DEC clustering head per
  branch (12 music and 20 dance clusters). Losses: ``branch_loss`` (Eq. 1, λ1·CE + λ2·KL(P‖Q))
  and, in phase 2, λ3·L_M + λ4·L_D + λ5·MSE(Z_M, Z_D) (Eq. 2) plus a variance hinge on each
  branch (VICReg's variance term, not in the paper: ``variance_hinge``), without which the MSE
  term collapses every embedding onto one point of the sphere.

Rhythm (13 common signatures):

- ``RhythmModel``: E_MR on ``(N, 2, 200)`` (onset strength, RMS per bar), E_DR on ``(N, 5, 60)``
  (kinematic curve, wrist curvatures, foot contacts per bar), and the shared classifier E_RS
  (three dense layers) fed with the rhythm code and a 32-d style vector of the same bar.
  ``rhythm_loss`` is Eq. 3: λ6·CE + λ7·E[G_r] (the expected weighted Hamming distance of the
  predicted distribution to the bar's true 8-slot signature).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from dancegraph.motion.features import MAIN_JOINTS
from dancegraph.rhythm.signatures import COMMON_BITS, SLOT_WEIGHTS

DIM = 32
MUSIC_CLUSTERS = 12
DANCE_CLUSTERS = 20
LAMBDAS = {"cls": 0.7, "dec": 0.3, "music": 0.5, "dance": 0.5, "pair": 5.0, "ce": 0.4, "ham": 0.6}
#: Weight of the variance hinge in phase 2 (a departure from Eq. 2, see ``variance_hinge``).
VAR_WEIGHT = 5.0
#: Per-dimension standard deviation the hinge asks of a batch: 1 = points spread evenly over the
#: sphere of radius √32 (their per-dimension variances sum to 32 minus the squared mean).
VAR_FLOOR = 1.0

#: Bones between the main joints (names of ``MAIN_JOINTS``): the E_D joint graph.
JOINT_EDGES: tuple[tuple[str, str], ...] = (
    ("hips", "chest"),
    ("chest", "neck"),
    ("neck", "head"),
    ("chest", "left_shoulder"),
    ("left_shoulder", "left_elbow"),
    ("left_elbow", "left_wrist"),
    ("chest", "right_shoulder"),
    ("right_shoulder", "right_elbow"),
    ("right_elbow", "right_wrist"),
    ("hips", "left_hip"),
    ("left_hip", "left_knee"),
    ("left_knee", "left_ankle"),
    ("left_ankle", "left_toe"),
    ("hips", "right_hip"),
    ("right_hip", "right_knee"),
    ("right_knee", "right_ankle"),
    ("right_ankle", "right_toe"),
)


def joint_adjacency() -> torch.Tensor:
    """``(18, 18)`` normalised adjacency D^-½ (A + I) D^-½ of the main-joint graph."""
    n = len(MAIN_JOINTS)
    a = torch.eye(n)
    for p, q in JOINT_EDGES:
        i, j = MAIN_JOINTS.index(p), MAIN_JOINTS.index(q)
        a[i, j] = a[j, i] = 1.0
    d = a.sum(1).rsqrt()
    return d[:, None] * a * d[None, :]


class _GRUHead(nn.Module):
    """Two GRU layers over a ``(N, T, C)`` sequence; the last hidden state → ``(N, 32)``, norm √32."""

    def __init__(self, in_dim: int, hidden: int = 64):
        super().__init__()
        self.gru = nn.GRU(in_dim, hidden, num_layers=2, batch_first=True)
        self.out = nn.Linear(hidden, DIM)

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        _, h = self.gru(seq)
        # on the sphere of radius √32: the paired MSE (λ5 = 5) cannot be won by shrinking every
        # embedding toward zero (sending them all to one point of the sphere is stopped by
        # ``variance_hinge``)
        return F.normalize(self.out(h[-1]), dim=1) * DIM**0.5


class MusicStyleNet(nn.Module):
    """E_M: ``(N, 1, 96, 800)`` log-mel dB → ``(N, 32)``.

    The conv trunk pools time by ``TIME_POOL`` (320 ms steps, 25 per window); ``embed_song`` runs
    it once over a whole song and cuts the windows from its output, so the overlapping per-bar
    windows of a song cost about one pass.
    """

    TIME_POOL = 32
    STEPS = 25

    def __init__(self):
        super().__init__()
        chans, pools = (1, 8, 16, 32, 32), ((2, 4), (2, 2), (2, 2), (3, 1))
        blocks: list[nn.Module] = [nn.AvgPool2d(2)]  # 10 ms, 96 bands → 20 ms, 48 bands
        for c_in, c_out, pool in zip(chans[:-1], chans[1:], pools, strict=True):
            blocks += [
                nn.Conv2d(c_in, c_out, 3, padding=1),
                nn.BatchNorm2d(c_out),
                nn.ReLU(),
                nn.MaxPool2d(pool),
            ]
        self.conv = nn.Sequential(*blocks)
        self.head = _GRUHead(32 * 2)  # 96 mel bands pooled to 2

    def trunk(self, x: torch.Tensor) -> torch.Tensor:
        """``(N, 1, 96, T)`` dB → ``(N, T // 32, 64)`` feature sequence."""
        h = self.conv((x + 40.0) / 20.0)  # dB (floor -100) to about unit scale
        return h.flatten(1, 2).transpose(1, 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.trunk(x))

    def embed_song(self, mel: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """Windows of one song: ``mel (96, T)`` dB, ``starts (B,)`` frame indices → ``(B, 32)``."""
        pad = int(starts.max()) + self.STEPS * self.TIME_POOL if len(starts) else mel.shape[1]
        pad = max(pad, mel.shape[1])
        full = torch.full((1, 1, mel.shape[0], pad), -100.0)
        full[0, 0, :, : mel.shape[1]] = mel
        seq = self.trunk(full)[0]  # (pad // 32, 64)
        idx = torch.round(starts.double() / self.TIME_POOL).long()
        win = idx[:, None] + torch.arange(self.STEPS)[None, :]
        return self.head(seq[win.clamp(max=seq.shape[0] - 1)])


class _GraphBlock(nn.Module):
    """Spatial graph convolution then a strided temporal convolution over ``(N, C, J, T)``."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.spatial = nn.Conv2d(c_in, c_out, 1)
        self.temporal = nn.Conv2d(c_out, c_out, (1, 9), stride=(1, 2), padding=(0, 4))
        # group norm, not batch norm: small batches of few styles made BN's running statistics
        # (used at inference) far from the batch statistics it trained with
        self.norm = nn.GroupNorm(4, c_out)

    def forward(self, x: torch.Tensor, adj: torch.Tensor) -> torch.Tensor:
        x = torch.einsum("ncjt,jk->nckt", self.spatial(x), adj)
        return F.relu(self.norm(self.temporal(F.relu(x))))


class DanceStyleNet(nn.Module):
    """E_D: ``(N, 3, 18, 240)`` main-joint positions (m) → ``(N, 32)``."""

    def __init__(self):
        super().__init__()
        self.register_buffer("adj", joint_adjacency())
        self.blocks = nn.ModuleList([_GraphBlock(6, 16), _GraphBlock(16, 32), _GraphBlock(32, 32)])
        self.head = _GRUHead(32)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # velocities (m/s) alongside positions: style lives as much in the movement
        vel = torch.diff(x, dim=-1, prepend=x[..., :1]) * 30.0
        h = torch.cat([x, vel], dim=1)
        for block in self.blocks:
            h = block(h, self.adj)
        return self.head(h.mean(dim=2).transpose(1, 2))  # pool the joints, GRU over time


class DEC(nn.Module):
    """Deep embedded clustering head: Student-t soft assignment to ``k`` learnt centres."""

    def __init__(self, k: int):
        super().__init__()
        self.centres = nn.Parameter(torch.randn(k, DIM))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        q = 1.0 / (1.0 + torch.cdist(z, self.centres) ** 2)
        return q / q.sum(1, keepdim=True)

    @staticmethod
    def loss(q: torch.Tensor) -> torch.Tensor:
        """KL(P‖Q) with DEC's sharpened target P (computed from Q, held fixed)."""
        with torch.no_grad():
            p = q**2 / q.sum(0, keepdim=True)
            p = p / p.sum(1, keepdim=True)
        return F.kl_div(q.clamp_min(1e-9).log(), p, reduction="batchmean")


def variance_hinge(z: torch.Tensor) -> torch.Tensor:
    """Mean over the 32 dimensions of max(0, ``VAR_FLOOR`` − std over the batch) of ``z (N, 32)``.

    VICReg's variance term (Bardes et al. 2022). λ5·MSE(Z_M, Z_D) is about 15 times the
    classification terms when phase 2 starts, and the cheapest way to lower it is to send every
    bar of both branches to one point (on the sphere: the output layer's bias outgrows the rest),
    which Eq. 2's cross-entropy, at most ln(classes) per branch, cannot outweigh. This term is zero
    while a batch stays spread and grows as it collapses.
    """
    return F.relu(VAR_FLOOR - torch.sqrt(z.var(dim=0) + 1e-4)).mean()


class StyleModel(nn.Module):
    """E_M and E_D with their classification and DEC heads; ``n_classes`` style classes."""

    def __init__(self, n_classes: int):
        super().__init__()
        self.music = MusicStyleNet()
        self.dance = DanceStyleNet()
        self.music_cls = nn.Linear(DIM, n_classes)
        self.dance_cls = nn.Linear(DIM, n_classes)
        self.music_dec = DEC(MUSIC_CLUSTERS)
        self.dance_dec = DEC(DANCE_CLUSTERS)

    def branch_loss(self, branch: str, x: torch.Tensor, y: torch.Tensor) -> tuple:
        """Eq. 1 for ``branch`` ('music' | 'dance'): ``(loss, z, logits)``."""
        z = getattr(self, branch)(x)
        logits = getattr(self, f"{branch}_cls")(z)
        dec = getattr(self, f"{branch}_dec")
        loss = LAMBDAS["cls"] * F.cross_entropy(logits, y) + LAMBDAS["dec"] * DEC.loss(dec(z))
        return loss, z, logits

    def paired_loss(
        self,
        xm: torch.Tensor,
        ym: torch.Tensor,
        xd: torch.Tensor,
        yd: torch.Tensor,
        pair_weight: float = LAMBDAS["pair"],
    ) -> tuple:
        """Eq. 2 and the variance hinge: λ3·L_M + λ4·L_D + ``pair_weight``·MSE(Z_M, Z_D) +
        ``VAR_WEIGHT``·(hinge(Z_M) + hinge(Z_D)); returns ``(loss, mse)``.

        ``pair_weight`` is λ5 once training has warmed it up (``train``)."""
        lm, zm, _ = self.branch_loss("music", xm, ym)
        ld, zd, _ = self.branch_loss("dance", xd, yd)
        mse = F.mse_loss(zm, zd)
        spread = VAR_WEIGHT * (variance_hinge(zm) + variance_hinge(zd))
        return LAMBDAS["music"] * lm + LAMBDAS["dance"] * ld + pair_weight * mse + spread, mse


class _RhythmEncoder(nn.Module):
    """Three strided 1-D conv layers over ``(N, C, L)`` → ``(N, 32)`` (slot positions kept)."""

    def __init__(self, channels: int, length: int):
        super().__init__()
        self.conv = nn.Sequential(
            nn.Conv1d(channels, 16, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv1d(16, 32, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv1d(32, 32, 5, stride=2, padding=2),
            nn.ReLU(),
        )
        out_len = length
        for _ in range(3):
            out_len = (out_len - 1) // 2 + 1
        self.out = nn.Linear(32 * out_len, DIM)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.conv(x).flatten(1))


class RhythmModel(nn.Module):
    """E_MR, E_DR and the shared signature classifier E_RS (→ logits over the 13 signatures)."""

    common_bits: torch.Tensor  # buffers (registered in __init__)
    slot_weights: torch.Tensor

    def __init__(self):
        super().__init__()
        self.music = _RhythmEncoder(2, 200)
        self.dance = _RhythmEncoder(5, 60)
        self.shared = nn.Sequential(
            nn.Linear(2 * DIM, 64),
            nn.ReLU(),
            nn.Linear(64, 64),
            nn.ReLU(),
            nn.Linear(64, len(COMMON_BITS)),
        )
        self.register_buffer("common_bits", torch.tensor(COMMON_BITS, dtype=torch.float32))
        self.register_buffer("slot_weights", torch.tensor(SLOT_WEIGHTS, dtype=torch.float32))

    def forward(self, branch: str, x: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
        """Logits ``(N, 13)`` for bars ``x`` of ``branch`` with their style vectors ``(N, 32)``."""
        return self.shared(torch.cat([getattr(self, branch)(x), style], dim=1))

    def rhythm_loss(self, logits: torch.Tensor, bits: torch.Tensor) -> torch.Tensor:
        """Eq. 3: λ6·CE(nearest common signature) + λ7·Σ_k p_k G_r(sig_k, true bits).

        ``bits (N, 8)`` the bars' true slot-indexed signatures (not necessarily common ones).
        """
        ham = (torch.abs(self.common_bits[None] - bits[:, None]) * self.slot_weights).sum(-1)
        target = ham.argmin(1)
        expected = (F.softmax(logits, 1) * ham).sum(1).mean()
        return LAMBDAS["ce"] * F.cross_entropy(logits, target) + LAMBDAS["ham"] * expected
