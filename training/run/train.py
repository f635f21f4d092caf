"""Train one preset of the relighting network on the synthetic light stage.

    python -m training.run.train --preset draft --minutes 25 --out runs/draft-01

The run folder gets ``recipe.json`` (every argument, git commit, data seed, versions, machine) at
the start, ``log.jsonl`` (losses over time) and ``checkpoint.pt`` (weights + config + recipe);
training/run/export.py copies the recipe into the model card. Training is time-boxed
(``--minutes``) or step-boxed (``--steps``): the learning-rate schedule, the progressive
resolutions and the starts of adversarial and temporal training are all fractions of that budget.
A step budget makes runs independent of the machine's load (the ablations use it); a time budget
fits a run into a slot.

``--measure-speed`` times training steps for fp32 / bf16 autocast / channels-last instead;
``--curve RUN`` prints a run's val curve; ``--render FOLDER`` renders samples for ``--cache``.
The pieces: options.py (the arguments), trainer.py (the step and the loop), schedule.py, ema.py,
batches.py, validation.py, lineage.py, recipe.py, speed.py.
"""

from __future__ import annotations

import torch

from ..data.dataset import make_dataset
from ..model import losses
from .batches import Batches, render_cache
from .options import parser
from .speed import measure_speed
from .trainer import train
from .validation import curve


def main(argv=None):
    args = parser().parse_args(argv)
    if args.curve:
        print(curve(args.curve))
        return
    if args.render:
        torch.set_num_threads(args.threads)
        render_cache(args.render, "train", args.resolution, args.seed, args.start, args.count,
                     sampling=losses.Switches.ablation(args.ablation).sampling)
        return
    if args.measure_speed:
        torch.set_num_threads(args.threads)
        ds = make_dataset("train", args.resolution, args.seed)
        batches = Batches(ds, args.batch, args.seed)
        b = next(batches)
        measure_speed(args, lambda: b)
        return
    print(f"run folder: {train(args)}")


if __name__ == "__main__":
    main()
