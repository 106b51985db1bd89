"""The cas service.

Content-addressed store and IPFS-compatible gateway:
every byte a robot gets can be checked against its CID.
"""
