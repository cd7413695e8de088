"""Train state, optimizer, the jitted train steps of each recipe, the loop and checkpoints."""
