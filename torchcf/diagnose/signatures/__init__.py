"""Step 1 of the loop: the residual series of the hybrid's best particles,
their signatures and the candidate effects they point to (the road, the
response times).
"""
