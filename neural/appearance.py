"""Per-photo appearance: an affine colour transform of each training photo (its exposure and white balance),
learned with the field so that the field need not bend its geometry to explain them.

c_photo = A_i c + b_i with A_i = I + D_i - mean_j D_j and b_i = e_i - mean_j e_j: the transforms' mean is the
identity by construction, so the field holds the photos' mean appearance and novel views (and held-out
photos) are rendered without a transform. The trainer adds weight * mean_i (||A_i - I||^2 + ||b_i||^2),
which keeps each transform near the mean so that it cannot absorb what the field should model.
"""

from __future__ import annotations

import torch
from torch import Tensor


class PhotoAppearance(torch.nn.Module):
    """Affine colour transforms of `num_photos` training photos (indexed as the training images)."""

    def __init__(self, num_photos: int) -> None:
        super().__init__()
        self.offset = torch.nn.Parameter(torch.zeros(num_photos, 3, 3))
        self.bias = torch.nn.Parameter(torch.zeros(num_photos, 3))

    def transforms(self) -> tuple[Tensor, Tensor]:
        """(A (N,3,3), b (N,3)), their mean the identity and zero."""
        deviation = self.offset - self.offset.mean(dim=0, keepdim=True)
        matrix = torch.eye(3, device=deviation.device, dtype=deviation.dtype) + deviation
        return matrix, self.bias - self.bias.mean(dim=0, keepdim=True)

    def forward(self, rgb: Tensor, photo: Tensor) -> Tensor:
        """c' = A_photo c + b_photo for colours rgb (R,3) of the training photos photo (R,)."""
        matrix, bias = self.transforms()
        return torch.einsum("rij,rj->ri", matrix[photo], rgb) + bias[photo]

    def penalty(self) -> Tensor:
        """mean_i ||A_i - I||^2 + ||b_i||^2."""
        matrix, bias = self.transforms()
        identity = torch.eye(3, device=matrix.device, dtype=matrix.dtype)
        return (matrix - identity).square().sum(dim=(1, 2)).mean() + bias.square().sum(dim=1).mean()
