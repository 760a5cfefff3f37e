"""Step 4: the loop's record (``loop.json``) and its report (``loop.md``,
figures).
"""
