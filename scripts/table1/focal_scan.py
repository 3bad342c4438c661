"""Photometric loss on labelled pairs vs the camera's focal length, network frozen (diagnostic)."""
# Usage: python scripts/table1/focal_scan.py CHECKPOINT BAG
import sys, torch, numpy as np
torch.set_num_threads(1)
from nocal_ros.checkpoint import load_checkpoint
from nocal_ros.data.bags import read_sequence
from nocal_ros.data.pairs import PairDataset
from nocal_ros.training import pair_loss
from nocal_ros.camera import CameraModel
ckpt, bag = sys.argv[1], sys.argv[2]
c = load_checkpoint(ckpt); model = c.model.eval()
seq = read_sequence(bag)
ds = PairDataset([seq], size=(80, 60), gap_range=(1, 8))
g = torch.Generator().manual_seed(5)
batches = [ds.sample(8, True, g) for _ in range(12)]
pix = [torch.randperm(4800, generator=g)[:1024] for _ in batches]
cam0 = c.cameras[0]
print("checkpoint camera fx", float(cam0.intrinsics()[0]))
for f in [540, 560, 580, 600, 620, 640, 660, 680]:
    cam = CameraModel(640, 480, fx=f)
    with torch.no_grad():
        loss = np.mean([float(pair_loss(model, [cam], b, p)[0].photometric) for b, p in zip(batches, pix)])
    print(f, f"{loss:.6f}")
