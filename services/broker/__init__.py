"""The broker service.

Verifiable outsourced computation:
staked provers, blinded commitments and majority results on chain.
"""
