"""Run real training steps from a checkpoint and print the focal gradient on each labelled step (diagnostic)."""
# Usage: python scripts/table1/train_probe.py CHECKPOINT BAG INTRINSICS_LR STEPS ENCODER_LR  (hypernetwork lr = 1.6 x encoder lr; 0 freezes the networks)
import sys, torch, numpy as np
torch.set_num_threads(1)
from nocal_ros.checkpoint import load_checkpoint
from nocal_ros.data.bags import read_sequence
from nocal_ros.data.pairs import PairDataset
from nocal_ros.training import optimisation_step, make_optimisers, training_config, PairSampler
import nocal_ros.training as T
c = load_checkpoint(sys.argv[1]); model = c.model; cam = c.cameras[0]; cam.set_stage("focal")
seq = read_sequence(sys.argv[2])
cfg = training_config({"learning_rates": {"intrinsics": float(sys.argv[3]), "encoder": float(sys.argv[5]), "hypernetwork": float(sys.argv[5]) * 1.6}})
ds = PairDataset([seq], size=(80, 60), gap_range=(1, 8))
sampler = PairSampler(ds, 4, 5, seed=3)
opt = make_optimisers(model, [cam], cfg["learning_rates"])
g = torch.Generator().manual_seed(4)
for step in range(int(sys.argv[4])):
    batch = sampler.next_batch(torch.device("cpu"))
    p = torch.randperm(4800, generator=g)[:1024]
    orig = opt["intrinsics"].step
    grad = {}
    def hook():
        grad["g"] = None if cam.log_fx_rel.grad is None else float(cam.log_fx_rel.grad)
        return orig()
    opt["intrinsics"].step = hook
    terms = optimisation_step(model, [cam], opt, batch, p, cfg)
    opt["intrinsics"].step = orig
    if grad["g"] is not None:
        print(step, f"f {float(cam.intrinsics()[0]):.1f} grad {grad['g']:.2e} ph {float(terms.photometric):.4f}")
