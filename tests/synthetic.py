"""Synthetic test fixtures shared by test files (plain helpers, not tests)."""
import torch

from activetouch.information import FREE, InformationField


def paddle():
    """Synthetic gripper: a 1 x 4 x 2 cm plate facing +x (h_I) and a small wrist block behind it (h only)."""
    xs, ys, zs = torch.meshgrid(torch.tensor([0.0, 0.005, 0.01]), torch.linspace(-0.02, 0.02, 9),
                                torch.linspace(-0.01, 0.01, 5), indexing="ij")
    plate = torch.stack([xs, ys, zs], -1).reshape(-1, 3)
    wrist = torch.tensor([[-0.02, 0.0, 0.0], [-0.03, 0.0, 0.0], [-0.02, 0.01, 0.0], [-0.02, -0.01, 0.0]])
    mask = torch.cat([torch.ones(len(plate), dtype=torch.bool), torch.zeros(4, dtype=torch.bool)])
    return torch.cat([plate, wrist]), mask


def toy_field(grid, centre, sigma=0.03):
    """All-free field with an information blob at ``centre``."""
    pts = grid.points()
    info = torch.exp(-((pts[:, :2] - torch.tensor(centre)) ** 2).sum(-1) / (2 * sigma**2)).reshape(grid.shape)
    probs = torch.zeros(*grid.shape, 3)
    probs[..., FREE] = 1.0
    lo = grid.lower.float()
    return InformationField(grid, probs, info, torch.zeros(*grid.shape, 3), lo, lo)
