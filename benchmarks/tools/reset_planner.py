"""A world-model checkpoint with its route planner back at its start (constant turn rate):
``python benchmarks/tools/reset_planner.py IN.pt OUT.pt``.

The route planner's last layer starts at zero, so zeroing it again gives exactly the untrained
planner while the rest of the model keeps what it learnt; the shipped ``wm-small`` is the
``small`` run's step-750 checkpoint so reset, because the planner trained alongside lowered the
validation forecast (see the README).
"""

from __future__ import annotations

import argparse

from t3fast.io.checkpoint import load_checkpoint, save_checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source")
    parser.add_argument("out")
    args = parser.parse_args()
    state = load_checkpoint(args.source)
    if state["config"]["task"]["model"].get("planner") != "route":
        raise SystemExit(f"{args.source}: not a route-planner world model (model.planner != 'route')")
    last = [key for key in state["model"] if key.startswith("planner.head.") and key.rsplit(".", 1)[-1] in
            ("weight", "bias")]
    layer = max(int(key.split(".")[2]) for key in last)
    for key in last:
        if int(key.split(".")[2]) == layer:
            state["model"][key].zero_()
    save_checkpoint(state, args.out)
    print(f"wrote {args.out}: planner.head.{layer} zeroed (constant turn rate), step {state.get('step')}")


if __name__ == "__main__":
    main()
