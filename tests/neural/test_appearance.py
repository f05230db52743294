"""Per-photo colour transforms: identity at first, their mean always the identity, fitted to the photos."""

import torch

from neural.appearance import PhotoAppearance


def test_the_transforms_start_at_the_identity_and_their_mean_stays_the_identity():
    appearance = PhotoAppearance(4)
    colours = torch.rand(10, 3)
    torch.testing.assert_close(appearance(colours, torch.zeros(10, dtype=torch.long)), colours)
    assert float(appearance.penalty().detach()) == 0.0
    with torch.no_grad():
        appearance.offset.normal_()
        appearance.bias.normal_()
    matrix, bias = appearance.transforms()
    torch.testing.assert_close(matrix.mean(dim=0), torch.eye(3))
    torch.testing.assert_close(bias.mean(dim=0), torch.zeros(3), atol=1e-6, rtol=0)


def test_per_photo_exposure_and_white_balance_are_recovered_from_the_photos_colours():
    """Photo 0 is 20 % darker, photo 1 warmer, photo 2 as the mean makes it: fitting A_i c + b_i to them."""
    gains = torch.tensor([[0.8, 0.8, 0.8], [1.1, 1.0, 0.9], [1.1, 1.2, 1.3]])
    colours = torch.rand(3000, 3)
    photo = torch.randint(3, (3000,))
    targets = colours * gains[photo]
    appearance = PhotoAppearance(3)
    optimizer = torch.optim.Adam(appearance.parameters(), lr=0.02)
    for _ in range(600):
        loss = torch.mean((appearance(colours, photo) - targets) ** 2)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    matrix, bias = appearance.transforms()
    torch.testing.assert_close(torch.diagonal(matrix, dim1=1, dim2=2), gains, atol=0.02, rtol=0)
    assert float(bias.detach().abs().max()) < 0.02
