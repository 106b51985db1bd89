// SPDX-License-Identifier: Apache-2.0
pragma solidity ^0.8.24;

/// @dev The part of Registry that AnchorLog relies on.
interface IRegistry {
    function STORAGE_NODE() external view returns (bytes32);

    function isActiveWithRole(address account, bytes32 role) external view returns (bool);
}

/// @title robocloud AnchorLog: Template Merkle Tree roots per storage node and epoch.
/// @notice A storage node publishes the TMT root of each epoch here, so that any robot can
/// check a record's inclusion proof with a hash function and one `eth_call`. Epochs strictly
/// increase per node (gaps are allowed), so a published root can never be replaced.
/// @dev Reverts use `require` strings prefixed with "AnchorLog: ".
contract AnchorLog {
    struct Anchor {
        bytes32 root;
        uint64 recordCount;
        uint64 timestamp;
        uint64 blockNumber;
    }

    struct NodeState {
        uint64 latestEpoch;
        uint64 anchorCount;
    }

    IRegistry public immutable registry;
    bytes32 public immutable storageNodeRole;

    mapping(address => mapping(uint64 => Anchor)) private _anchors;
    mapping(address => NodeState) private _nodes;

    event Anchored(
        address indexed node,
        uint64 indexed epoch,
        bytes32 root,
        uint64 recordCount,
        uint64 timestamp
    );

    constructor(IRegistry registry_) {
        require(address(registry_).code.length > 0, "AnchorLog: registry is not a contract");
        registry = registry_;
        storageNodeRole = registry_.STORAGE_NODE();
    }

    function anchor(uint64 epoch, bytes32 tmtRoot, uint64 recordCount) external {
        require(
            registry.isActiveWithRole(msg.sender, storageNodeRole),
            "AnchorLog: caller is not an active storage node"
        );
        require(tmtRoot != bytes32(0), "AnchorLog: empty root");
        NodeState storage node = _nodes[msg.sender];
        require(
            node.anchorCount == 0 || epoch > node.latestEpoch,
            "AnchorLog: epoch not increasing"
        );
        _anchors[msg.sender][epoch] = Anchor(
            tmtRoot, recordCount, uint64(block.timestamp), uint64(block.number)
        );
        node.latestEpoch = epoch;
        node.anchorCount += 1;
        emit Anchored(msg.sender, epoch, tmtRoot, recordCount, uint64(block.timestamp));
    }

    /// @notice The root `node` anchored for `epoch`, or zero when it anchored none
    /// (an anchored root is never zero).
    function rootAt(address node, uint64 epoch) external view returns (bytes32) {
        return _anchors[node][epoch].root;
    }

    /// @notice The full anchor of `node` at `epoch`; all fields are zero when there is none.
    function anchorAt(address node, uint64 epoch)
        external
        view
        returns (bytes32 root, uint64 recordCount, uint64 timestamp, uint64 blockNumber)
    {
        Anchor storage a = _anchors[node][epoch];
        return (a.root, a.recordCount, a.timestamp, a.blockNumber);
    }

    /// @notice The most recent anchor of `node`; reverts when it has anchored nothing.
    function latest(address node)
        external
        view
        returns (uint64 epoch, bytes32 root, uint64 recordCount, uint64 timestamp)
    {
        NodeState storage state = _nodes[node];
        require(state.anchorCount > 0, "AnchorLog: node has no anchors");
        Anchor storage a = _anchors[node][state.latestEpoch];
        return (state.latestEpoch, a.root, a.recordCount, a.timestamp);
    }

    function anchorCount(address node) external view returns (uint64) {
        return _nodes[node].anchorCount;
    }
}
