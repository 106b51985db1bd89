"""The ledger service.

The Ethereum chain and its contracts:
robot registry, advertisements and root anchoring.
"""
