"""The policy node: a trained chapter-7 network (model.py) rolled out by the compiled loop
(compiled.py) on the latest scene, or the naive replay; plans for the trajectory optimizer.
Training is in learning/, evaluation in evaluation/."""
