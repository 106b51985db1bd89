"""The fl service.

Federated learning with Byzantine-robust aggregation
and an on-chain quorum on each round's aggregate.
"""
