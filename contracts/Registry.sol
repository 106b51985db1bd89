// SPDX-License-Identifier: Apache-2.0
pragma solidity ^0.8.24;

/// @title robocloud Registry: robots, their roles, and first-advertiser timestamping of CIDs.
/// @notice Robots register themselves with the binary CID of their metadata. In the `Open`
/// registration mode (development) that is enough; in the `Approved` mode a registration
/// waits until the admin or a robot with the registrar role approves (or rejects) it, so that
/// "registered" means someone vouched for the robot. The admin (the deployer) grants roles,
/// sets the mode and may suspend a robot; a robot may deactivate itself. Any active robot may
/// advertise a CID: the first advertiser and its block timestamp are kept forever, and every
/// advertisement is logged so that indexers see who else holds the data.
/// @dev Reverts use `require` strings prefixed with "Registry: " so that any Ethereum client
/// can show them without this contract's ABI.
contract Registry {
    bytes32 public constant STORAGE_NODE = keccak256("robocloud.role.storage_node");
    bytes32 public constant REVIEWER = keccak256("robocloud.role.reviewer");
    bytes32 public constant AGGREGATOR = keccak256("robocloud.role.aggregator");
    bytes32 public constant REGISTRAR = keccak256("robocloud.role.registrar");

    enum RegistrationMode {
        Open,
        Approved
    }

    /// CIDv1 with a SHA-256 multihash is 36 bytes; the bound keeps storage and gas predictable.
    uint256 public constant MAX_CID_LENGTH = 128;

    struct Robot {
        bytes metadataCid;
        uint64 registeredAt;
        bool registered;
        bool active;
        bool suspended;
        bool pending;
    }

    struct Advertisement {
        address firstAdvertiser;
        uint64 firstTimestamp;
        uint64 firstBlock;
        uint32 count;
        bytes descriptionCid;
    }

    address public admin;
    uint256 public robotCount;
    uint256 public pendingCount;
    RegistrationMode public registrationMode;

    mapping(address => Robot) private _robots;
    mapping(address => mapping(bytes32 => bool)) private _roles;
    mapping(bytes32 => Advertisement) private _advertisements;

    event RobotRegistered(address indexed robot, bytes metadataCid, uint64 timestamp);
    event RegistrationRequested(address indexed robot, bytes metadataCid, uint64 timestamp);
    event RegistrationApproved(address indexed robot, address indexed registrar);
    event RegistrationRejected(address indexed robot, address indexed registrar);
    event RegistrationModeChanged(RegistrationMode mode);
    event MetadataUpdated(address indexed robot, bytes metadataCid);
    event RobotActivationChanged(address indexed robot, bool active);
    event RobotSuspensionChanged(address indexed robot, bool suspended);
    event RoleGranted(bytes32 indexed role, address indexed account);
    event RoleRevoked(bytes32 indexed role, address indexed account);
    event AdminTransferred(address indexed previousAdmin, address indexed newAdmin);
    event Advertised(
        bytes32 indexed cidHash,
        address indexed advertiser,
        bytes cid,
        bytes descriptionCid,
        bool first,
        uint64 timestamp
    );

    modifier onlyAdmin() {
        require(msg.sender == admin, "Registry: caller is not the admin");
        _;
    }

    /// The admin, or an active robot holding the registrar role.
    modifier onlyRegistrar() {
        require(
            msg.sender == admin || (_roles[msg.sender][REGISTRAR] && isActive(msg.sender)),
            "Registry: caller is not a registrar"
        );
        _;
    }

    modifier onlyRegistered() {
        require(_robots[msg.sender].registered, "Registry: caller is not registered");
        _;
    }

    constructor() {
        admin = msg.sender;
        emit AdminTransferred(address(0), msg.sender);
    }

    // ----- robots -----

    /// @notice Register the caller; in the Approved mode the registration waits for a registrar.
    function register(bytes calldata metadataCid) external {
        _checkCid(metadataCid, "Registry: empty metadata CID");
        Robot storage robot = _robots[msg.sender];
        require(!robot.registered, "Registry: already registered");
        require(!robot.pending, "Registry: registration already pending");
        robot.metadataCid = metadataCid;
        robot.registeredAt = uint64(block.timestamp);
        if (registrationMode == RegistrationMode.Approved) {
            robot.pending = true;
            pendingCount += 1;
            emit RegistrationRequested(msg.sender, metadataCid, uint64(block.timestamp));
            return;
        }
        _admit(msg.sender);
    }

    /// @notice Admit a pending robot; its registration time becomes the approval's.
    function approve(address account) external onlyRegistrar {
        Robot storage robot = _robots[account];
        require(robot.pending, "Registry: no pending registration");
        robot.pending = false;
        pendingCount -= 1;
        robot.registeredAt = uint64(block.timestamp);
        emit RegistrationApproved(account, msg.sender);
        _admit(account);
    }

    /// @notice Refuse a pending robot; it may ask again.
    function reject(address account) external onlyRegistrar {
        Robot storage robot = _robots[account];
        require(robot.pending, "Registry: no pending registration");
        delete _robots[account];
        pendingCount -= 1;
        emit RegistrationRejected(account, msg.sender);
    }

    function isPending(address account) external view returns (bool) {
        return _robots[account].pending;
    }

    function setRegistrationMode(RegistrationMode mode) external onlyAdmin {
        require(registrationMode != mode, "Registry: registration mode unchanged");
        registrationMode = mode;
        emit RegistrationModeChanged(mode);
    }

    function updateMetadata(bytes calldata metadataCid) external onlyRegistered {
        _checkCid(metadataCid, "Registry: empty metadata CID");
        _robots[msg.sender].metadataCid = metadataCid;
        emit MetadataUpdated(msg.sender, metadataCid);
    }

    function deactivate() external onlyRegistered {
        Robot storage robot = _robots[msg.sender];
        require(robot.active, "Registry: already inactive");
        robot.active = false;
        emit RobotActivationChanged(msg.sender, false);
    }

    function reactivate() external onlyRegistered {
        Robot storage robot = _robots[msg.sender];
        require(!robot.active, "Registry: already active");
        robot.active = true;
        emit RobotActivationChanged(msg.sender, true);
    }

    function isRegistered(address account) external view returns (bool) {
        return _robots[account].registered;
    }

    /// @notice True for a registered robot that has not deactivated itself and is not suspended.
    function isActive(address account) public view returns (bool) {
        Robot storage robot = _robots[account];
        return robot.registered && robot.active && !robot.suspended;
    }

    function getRobot(address account)
        external
        view
        returns (
            bytes memory metadataCid,
            uint64 registeredAt,
            bool registered,
            bool active,
            bool suspended
        )
    {
        Robot storage robot = _robots[account];
        return (robot.metadataCid, robot.registeredAt, robot.registered, robot.active, robot.suspended);
    }

    // ----- administration -----

    function setSuspended(address account, bool suspended) external onlyAdmin {
        Robot storage robot = _robots[account];
        require(robot.registered, "Registry: account is not registered");
        require(robot.suspended != suspended, "Registry: suspension unchanged");
        robot.suspended = suspended;
        emit RobotSuspensionChanged(account, suspended);
    }

    function grantRole(address account, bytes32 role) external onlyAdmin {
        _checkRole(role);
        require(_robots[account].registered, "Registry: account is not registered");
        require(!_roles[account][role], "Registry: role already granted");
        _roles[account][role] = true;
        emit RoleGranted(role, account);
    }

    function revokeRole(address account, bytes32 role) external onlyAdmin {
        _checkRole(role);
        require(_roles[account][role], "Registry: role not granted");
        _roles[account][role] = false;
        emit RoleRevoked(role, account);
    }

    /// @notice Role membership only; callers that authorize should also check `isActive`,
    /// or use `isActiveWithRole`.
    function hasRole(address account, bytes32 role) public view returns (bool) {
        return _roles[account][role];
    }

    function isActiveWithRole(address account, bytes32 role) external view returns (bool) {
        return _roles[account][role] && isActive(account);
    }

    function transferAdmin(address newAdmin) external onlyAdmin {
        require(newAdmin != address(0), "Registry: new admin is the zero address");
        emit AdminTransferred(admin, newAdmin);
        admin = newAdmin;
    }

    // ----- advertisements -----

    /// @notice Announce that the caller holds `cid`, described by `descriptionCid` (may be empty).
    /// The first advertisement of a CID fixes its first advertiser and timestamp.
    function advertise(bytes calldata cid, bytes calldata descriptionCid) external {
        require(isActive(msg.sender), "Registry: advertiser is not an active robot");
        _checkCid(cid, "Registry: empty CID");
        require(descriptionCid.length <= MAX_CID_LENGTH, "Registry: CID too long");
        bytes32 cidHash = keccak256(cid);
        Advertisement storage ad = _advertisements[cidHash];
        bool first = ad.count == 0;
        if (first) {
            ad.firstAdvertiser = msg.sender;
            ad.firstTimestamp = uint64(block.timestamp);
            ad.firstBlock = uint64(block.number);
            ad.descriptionCid = descriptionCid;
        }
        ad.count += 1;
        emit Advertised(cidHash, msg.sender, cid, descriptionCid, first, uint64(block.timestamp));
    }

    function getAdvertisement(bytes calldata cid)
        external
        view
        returns (
            address firstAdvertiser,
            uint64 firstTimestamp,
            uint64 firstBlock,
            uint32 count,
            bytes memory descriptionCid
        )
    {
        Advertisement storage ad = _advertisements[keccak256(cid)];
        return (ad.firstAdvertiser, ad.firstTimestamp, ad.firstBlock, ad.count, ad.descriptionCid);
    }

    // ----- internal -----

    function _admit(address account) private {
        Robot storage robot = _robots[account];
        robot.registered = true;
        robot.active = true;
        robotCount += 1;
        emit RobotRegistered(account, robot.metadataCid, robot.registeredAt);
    }

    function _checkCid(bytes calldata cid, string memory emptyReason) private pure {
        require(cid.length > 0, emptyReason);
        require(cid.length <= MAX_CID_LENGTH, "Registry: CID too long");
    }

    function _checkRole(bytes32 role) private pure {
        require(
            role == STORAGE_NODE || role == REVIEWER || role == AGGREGATOR || role == REGISTRAR,
            "Registry: unknown role"
        );
    }
}
