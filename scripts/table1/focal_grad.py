"""Per-batch gradient of the photometric loss w.r.t. the camera's log focal, network frozen (diagnostic)."""
# Usage: python scripts/table1/focal_grad.py CHECKPOINT BAG FOCAL [FOCAL ...]
import sys, torch, numpy as np
torch.set_num_threads(1)
from nocal_ros.checkpoint import load_checkpoint
from nocal_ros.data.bags import read_sequence
from nocal_ros.data.pairs import PairDataset
from nocal_ros.training import pair_loss
from nocal_ros.camera import CameraModel
c = load_checkpoint(sys.argv[1]); model = c.model
seq = read_sequence(sys.argv[2])
ds = PairDataset([seq], size=(80, 60), gap_range=(1, 8))
g = torch.Generator().manual_seed(7)
for f in [float(a) for a in sys.argv[3:]]:
    grads = []
    for _ in range(24):
        b = ds.sample(4, True, g); p = torch.randperm(4800, generator=g)[:1024]
        cam = CameraModel(640, 480, fx=f); cam.set_stage("focal")
        loss = pair_loss(model, [cam], b, p)[0].photometric
        gx, gy = torch.autograd.grad(loss, [cam.log_fx_rel, cam.log_fy_rel])
        grads.append(float(gx + gy) / 2)
    grads = np.array(grads)
    print(f"f {f}: mean {grads.mean():.3e} std {grads.std():.3e} snr {grads.mean()/grads.std():.3f} positive {np.mean(grads>0):.2f}")
