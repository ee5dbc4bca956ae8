import threading

import torch

from tiger.language.feature_maps import ResidentMaps, map_loader
from tiger.render import Camera


class _Store:
    """A FeatureSet stand-in: maps by image name, recording which thread read each."""

    def __init__(self, names, maps):
        self.names, self._maps, self.threads = names, dict(zip(names, maps)), {}

    def load(self, name):
        self.threads[name] = threading.current_thread().name
        feats, valid = self._maps[name]
        return feats.clone(), valid.clone()


def _camera(name, h, w):
    K = torch.tensor([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]])
    return Camera(viewmat=torch.eye(4), K=K, width=w, height=h, image_name=name)


def test_maps_from_a_store_are_read_on_threads_in_camera_order():
    g = torch.Generator().manual_seed(0)
    names = [f"img_{k:02d}.png" for k in range(6)]
    maps = [(torch.randn(4 + k, 5, 3, generator=g).half(), torch.rand(4 + k, 5, generator=g) > 0.3) for k in range(6)]
    store = _Store(names, maps)
    cams = [_camera(n, 4 + k, 5) for k, n in reversed(list(enumerate(names)))]  # cameras in another order
    resident = ResidentMaps(map_loader(store, cams), len(cams), None, torch.device("cpu"))
    assert resident.sizes == [(4 + k, 5) for k in reversed(range(6))]
    for i, (k, _) in enumerate(reversed(list(enumerate(names)))):
        view = resident.get(i)
        assert torch.equal(view.features, maps[k][0]) and torch.equal(view.valid, maps[k][1])
        assert view.n_valid == int(maps[k][1].sum())
    assert all(t != threading.current_thread().name for t in store.threads.values())


def test_a_plain_callable_is_called_in_order_on_the_callers_thread():
    seen = []

    def load(i):
        seen.append((i, threading.current_thread().name))
        return torch.full((2, 3, 4), float(i))

    resident = ResidentMaps(load, 3, None, torch.device("cpu"))
    assert seen == [(i, threading.current_thread().name) for i in range(3)]
    assert [float(resident.get(i).features[0, 0, 0]) for i in range(3)] == [0.0, 1.0, 2.0]
