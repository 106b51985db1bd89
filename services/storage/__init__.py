"""The storage service.

Typed records over ROS data, the Template Merkle Tree with on-chain anchors,
rich queries and the semantic knowledge base.
"""
