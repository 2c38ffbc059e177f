"""Discovery: what the replay gets wrong, which effect explains it, and what the fix is worth."""
