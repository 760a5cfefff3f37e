"""Step 2's machinery: an effect's arm fitted beside the pool's (populations,
local search, per-pair refits, absorption, the validation designs, the
ledger of finished fits).
"""
