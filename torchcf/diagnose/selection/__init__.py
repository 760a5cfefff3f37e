"""Step 2's decisions: the forward selection of effects by exact tests, their
power, and the model class judged on the test pairs.
"""
