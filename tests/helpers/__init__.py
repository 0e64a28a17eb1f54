"""The helpers the tests share: one place, never imported from another test file."""
