"""Synthetic test fixtures shared by test files (plain helpers, not tests)."""
import torch


def paddle():
    """Synthetic gripper: a 1 x 4 x 2 cm plate facing +x (h_I) and a small wrist block behind it (h only)."""
    xs, ys, zs = torch.meshgrid(torch.tensor([0.0, 0.005, 0.01]), torch.linspace(-0.02, 0.02, 9),
                                torch.linspace(-0.01, 0.01, 5), indexing="ij")
    plate = torch.stack([xs, ys, zs], -1).reshape(-1, 3)
    wrist = torch.tensor([[-0.02, 0.0, 0.0], [-0.03, 0.0, 0.0], [-0.02, 0.01, 0.0], [-0.02, -0.01, 0.0]])
    mask = torch.cat([torch.ones(len(plate), dtype=torch.bool), torch.zeros(4, dtype=torch.bool)])
    return torch.cat([plate, wrist]), mask
