"""Does stage 1 break out on other seeds? (docs/results/table3_300k.md, "The cause, and the fix")

python docs/results/table3_300k/stage1_survey.py SEEDS [UPDATES]   e.g. 10,11,12 400

The kept mixed B config without its pool (constant cars), per seed: 8 batches drawn first (the
states on which the original check counted dead units; they shift the sampling stream against a
run of that seed), then the trainer's own stage-1 updates, and the mean TD loss over the last 50.
Prints one line per seed. Run from the repository root (the example prior knowledge is read
from, or recorded into, outputs/data).
"""
import sys
import tempfile
from pathlib import Path

from omegaconf import OmegaConf

from memrl.dqn.loop import Trainer
from memrl.train import prior_knowledge

seeds = [int(s) for s in sys.argv[1].split(",")]
updates = int(sys.argv[2]) if len(sys.argv) > 2 else 400
base = OmegaConf.load("docs/results/mixed_100k/stage1_flat/B_mixed_s0/config.yaml")
base.paths.data_dir, base.progress = "outputs/data", True
base.env.opponent.type, base.env.opponent.pool = "constant", []
demos = prior_knowledge(base)
for seed in seeds:
    cfg = base.copy()
    cfg.seed = seed
    with tempfile.TemporaryDirectory() as out:
        t = Trainer(cfg, Path(out), demos=demos)
        for _ in range(8):
            t.stage.buffer.sample()
        losses = [t.learner.update(t.stage.buffer.sample()) for _ in range(updates)]
    print(f"seed {seed}: mean loss over updates {updates - 49}-{updates} {sum(losses[-50:]) / 50:.3f}",
          flush=True)
