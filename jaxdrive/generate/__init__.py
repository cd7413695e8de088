"""Long-horizon generation over one model API: recurrent rollout, divide-and-conquer,
coarse-to-(re)fine with JDC, coarse + parallel fine, and streaming."""
